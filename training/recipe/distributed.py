"""Data-parallel training through ``torchrun``: process group, DDP wrapping, sharded sampling.

``torchrun --nproc_per_node=N -m msdnet.training.cli ...`` starts N processes and sets
``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``, ``MASTER_ADDR`` and ``MASTER_PORT``; without
those variables everything here degrades to a single process (no process group).
Backend: gloo on CPU; on CUDA nccl, with gloo kept for CPU tensors.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import Dataset, DistributedSampler


@dataclass(frozen=True)
class DistInfo:
    """Where this process stands in the job."""

    rank: int = 0  # global rank (0 writes checkpoints and logs)
    world_size: int = 1  # processes in the job
    local_rank: int = 0  # rank on this machine (picks the CUDA device)

    @property
    def is_main(self) -> bool:
        """True on the one process that writes files and draws the progress bar."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        """True when a process group is (to be) used."""
        return self.world_size > 1


def init_distributed(device: torch.device) -> DistInfo:
    """Join the torchrun process group if ``WORLD_SIZE`` > 1; returns this process's place."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    info = DistInfo(int(os.environ["RANK"]), world, int(os.environ.get("LOCAL_RANK", "0")))
    if not dist.is_initialized():
        # CUDA: nccl for the model's tensors, gloo for the loop's small CPU reductions.
        backend = "cpu:gloo,cuda:nccl" if device.type == "cuda" else "gloo"
        dist.init_process_group(backend=backend, rank=info.rank, world_size=world)
    return info


def shutdown_distributed() -> None:
    """Leave the process group if one was joined."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


class LossModule(torch.nn.Module):
    """``forward(batch) -> model.losses(batch)``: DDP only syncs gradients through forward."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, batch: Any) -> dict[str, torch.Tensor]:
        return self.model.losses(batch)


def wrap_for_training(model: torch.nn.Module, info: DistInfo) -> torch.nn.Module:
    """The module to call in the loop: ``LossModule`` inside DDP when distributed.

    Every trainable parameter of the three models reaches the loss on every step (a term
    with nothing to average is multiplied by zero, not skipped), so DDP does not search for
    unused parameters; frozen ones (the student's teacher) are not synchronised at all.
    """
    wrapped = LossModule(model)
    if not info.distributed:
        return wrapped
    device_ids = [info.local_rank] if next(model.parameters()).is_cuda else None
    return DistributedDataParallel(wrapped, device_ids=device_ids, find_unused_parameters=False)


def all_reduce_sum(values: torch.Tensor, info: DistInfo) -> torch.Tensor:
    """Sum of ``values`` over all processes (the tensor itself when single-process)."""
    if info.distributed:
        dist.all_reduce(values, op=dist.ReduceOp.SUM)
    return values


class EpochSampler(DistributedSampler):
    """DistributedSampler (seeded shuffle per epoch, one shard per rank) that can skip.

    ``set_position(epoch, skip)`` fixes the epoch's permutation and drops this rank's first
    ``skip`` samples, so a run resumed mid-epoch sees exactly the batches it had left.
    With ``with_epoch`` it yields ``(epoch, index)`` keys instead of indices, for a dataset that
    draws a per-sample augmentation from them (same key, same transform, on resume too).
    """

    def __init__(self, dataset: Dataset, info: DistInfo, seed: int, with_epoch: bool = False) -> None:
        super().__init__(dataset, num_replicas=info.world_size, rank=info.rank, shuffle=True, seed=seed)
        self.skip = 0
        self.with_epoch = with_epoch

    def set_position(self, epoch: int, skip: int) -> None:
        """Choose the epoch (permutation) and how many of this rank's samples to drop."""
        self.set_epoch(epoch)
        self.skip = skip

    def __iter__(self) -> Iterator[int] | Iterator[tuple[int, int]]:
        order = list(super().__iter__())[self.skip :]
        return iter([(self.epoch, i) for i in order] if self.with_epoch else order)

    def __len__(self) -> int:
        return max(0, super().__len__() - self.skip)
