"""The training loop: Adam + OneCycleLR, gradient clipping, validation, checkpoints, resume.

Determinism: the model is built after ``torch.manual_seed(seed)`` (same weights on every
rank); the sample order of epoch ``e`` is the seeded permutation of ``EpochSampler``; and
the torch / numpy / random generators are reseeded before every step from
``(seed, rank, step)`` and before validation from ``(seed, rank, VAL_STREAM)``. No generator
state has to be stored, and a run resumed from any checkpoint (epoch end or, with
``save_every``, mid-epoch) continues bit for bit like the uninterrupted run.

Files in ``spec.out`` (rank 0 only): ``last/`` and ``best/`` checkpoints (see checkpoint.py)
and ``log.jsonl``, one JSON object per line with an ``event`` of ``start``, ``step``,
``epoch`` or ``stop``.
"""

from __future__ import annotations

import json
import math
import random
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler
from tqdm import tqdm

from msdnet.runtime.errors import MsdnetError
from msdnet.training.config import ModelConfig, TrainConfig
from msdnet.training.recipe.checkpoint import (
    CheckpointState,
    config_diff,
    load_training_state,
    load_weights,
    read_checkpoint,
    save_checkpoint,
)
from msdnet.training.recipe.distributed import DistInfo, EpochSampler, all_reduce_sum, wrap_for_training

VAL_STREAM = 2**31 - 1  # the "step" key of the validation seed


class NonFiniteLoss(MsdnetError):
    """A loss term became NaN or Inf: the run stops (``last`` keeps the previous good state)."""


@dataclass(frozen=True)
class RunSpec:
    """What one ``train`` call does, besides the model and data."""

    kind: str  # teacher | student | r2ldm (recorded; checked on resume)
    out: Path  # run folder: last/, best/, log.jsonl
    epochs: int  # epochs planned for the whole run (fixes the OneCycleLR length)
    resume: bool = False  # continue from out/last (weights, optimizer, scheduler, position)
    save_every: int = 0  # also save out/last every N steps inside an epoch (0: epoch ends only)
    log_every: int = 10  # steps between "step" lines in log.jsonl
    metric_frames: int | None = 64  # validation frames that also get occupancy metrics (None: all)
    stop_after: int | None = None  # return after this many epochs in this call (a clean "kill")
    device: str = "cpu"  # torch device of model and batches
    teacher: str | None = None  # teacher checkpoint path (student / r2ldm), recorded
    dataset: dict[str, Any] = field(default_factory=dict)  # dataset description, recorded
    init: str | None = None  # checkpoint whose weights started the run, recorded


# Per-batch metric counts, summed over the validation set: ``f(model, batch) -> {name: count}``.
MetricsFn = Callable[[torch.nn.Module, Any], dict[str, float]]


def reseed(seed: int, rank: int, step: int) -> None:
    """Seed torch, numpy and random from ``(seed, rank, step)`` (SeedSequence mixing)."""
    s = int(np.random.SeedSequence([seed, rank, step]).generate_state(1, dtype=np.uint64)[0])
    torch.manual_seed(s)
    np.random.seed(s % 2**32)
    random.seed(s)


def _to_device(batch: Any, device: torch.device) -> Any:
    if device.type == "cpu" or not hasattr(batch, "to"):
        return batch
    return batch.to(device)


def _batch_size(batch: Any) -> int:
    return int(getattr(batch, "batch_size", 1))


class JsonLog:
    """Append-only JSON-lines log; each line is flushed as written."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)

    def write(self, event: str, **fields: Any) -> None:
        """Append ``{"event": event, "time": unix seconds, **fields}``."""
        line = json.dumps({"event": event, "time": round(time.time(), 3), **fields})
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(line + "\n")


def _check_finite(losses: dict[str, torch.Tensor], state: CheckpointState, info: DistInfo) -> None:
    """Raise NonFiniteLoss on every rank when any rank has a non-finite term."""
    names = list(losses)
    bad = torch.tensor([0.0 if bool(torch.isfinite(losses[k]).all()) else 1.0 for k in names])
    bad = all_reduce_sum(bad, info)
    if not bool(bad.any()):
        return
    # Name the component terms to blame; the total only when it alone is non-finite.
    named = [k for i, k in enumerate(names) if bad[i] > 0 and k != "loss"] or ["loss"]
    parts = []
    for k in named:
        v = losses[k].detach().float().sum().item()
        parts.append(f"{k}={v}" if not math.isfinite(v) else f"{k} non-finite on another rank")
    raise NonFiniteLoss(
        None,
        f"non-finite loss at epoch {state.epoch + 1}, step {state.step + 1}: {', '.join(parts)}"
        " (lower the learning rate or check the input data)",
    )


def occupancy_scores(counts: dict[str, float]) -> dict[str, float]:
    """Precision, recall and IoU of occupied voxels from summed ``occ_tp/occ_fp/occ_fn``."""
    if not {"occ_tp", "occ_fp", "occ_fn"} <= counts.keys():
        return {}
    tp, fp, fn = counts["occ_tp"], counts["occ_fp"], counts["occ_fn"]
    return {
        "occ_precision": tp / max(tp + fp, 1.0),
        "occ_recall": tp / max(tp + fn, 1.0),
        "occ_iou": tp / max(tp + fp + fn, 1.0),
    }


def occupancy_counts(model: torch.nn.Module, batch: Any, modality: str) -> dict[str, float]:
    """Full-scale occupancy of ``model.predict`` at ``cfg.threshold`` against the LiDAR target.

    modality: "lidar" (teacher) or "radar" (student, R2LDM) picks the input. Returns summed
    voxel counts ``occ_tp``, ``occ_fp``, ``occ_fn`` (true / false positives, misses).
    """
    occ, _ = model.predict(getattr(batch, modality))  # (B, D, H, W) in [0, 1]
    pred = occ > model.cfg.threshold
    target = batch.targets[-1][0] > 0.5  # full scale (B, D, H, W)
    return {
        "occ_tp": float((pred & target).sum()),
        "occ_fp": float((pred & ~target).sum()),
        "occ_fn": float((~pred & target).sum()),
    }


def _reduce_means(sums: dict[str, float], count: float, info: DistInfo) -> dict[str, float]:
    """Mean of each summed term over all ranks; keys in the same order on every rank."""
    keys = sorted(sums)
    t = torch.tensor([sums[k] for k in keys] + [count], dtype=torch.float64)
    t = all_reduce_sum(t, info)
    n = max(t[-1].item(), 1.0)
    return {k: t[i].item() / n for i, k in enumerate(keys)}


def evaluate(
    model: torch.nn.Module,
    dataset: Dataset,
    collate_fn: Callable[[list[Any]], Any],
    train_cfg: TrainConfig,
    info: DistInfo,
    device: torch.device,
    metrics_fn: MetricsFn | None = None,
    metric_frames: int | None = None,
) -> dict[str, float]:
    """Validation: mean of every loss term (``val_<term>``) plus summed metric counts
    (``metrics_fn`` on the first ``metric_frames`` frames, all when None; the count of
    frames it saw is ``metric_frames``).

    Each rank takes a DistributedSampler shard (padded by repeating frames so the shards
    are equal); sums are all-reduced so every rank returns the same numbers.
    """
    sampler = DistributedSampler(dataset, num_replicas=info.world_size, rank=info.rank, shuffle=False)
    loader = DataLoader(dataset, batch_size=train_cfg.batch_size, sampler=sampler, collate_fn=collate_fn)
    was_training = model.training
    model.eval()
    reseed(train_cfg.seed, info.rank, VAL_STREAM)
    sums: dict[str, float] = {}
    counts: dict[str, float] = {}
    frames = 0
    per_rank = math.ceil((metric_frames or 0) / info.world_size)
    with torch.no_grad():
        for batch in loader:
            batch = _to_device(batch, device)
            n = _batch_size(batch)
            for k, v in model.losses(batch).items():
                sums[f"val_{k}"] = sums.get(f"val_{k}", 0.0) + float(v) * n
            if metrics_fn is not None and (metric_frames is None or frames < per_rank):
                counts["metric_frames"] = counts.get("metric_frames", 0.0) + n
                for k, v in metrics_fn(model, batch).items():
                    counts[k] = counts.get(k, 0.0) + float(v)
            frames += n
    model.train(was_training)
    out = _reduce_means(sums, frames, info)
    if counts:
        keys = sorted(counts)
        total = all_reduce_sum(torch.tensor([counts[k] for k in keys], dtype=torch.float64), info)
        out.update({k: total[i].item() for i, k in enumerate(keys)})
    return out


def _resume_state(
    spec: RunSpec,
    cfg: ModelConfig,
    train_cfg: TrainConfig,
    info: DistInfo,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler,
    ema: dict[str, torch.Tensor] | None = None,
) -> CheckpointState:
    """Load out/last into model / optimizer / scheduler (/ the weights' EMA) after checking it
    fits this run."""
    folder, saved_cfg, state = read_checkpoint(spec.out / "last")
    problems = []
    if state.kind != spec.kind:
        problems.append(f"kind is {state.kind}, not {spec.kind}")
    if saved_cfg != cfg:
        problems.append("model config differs: " + ", ".join(config_diff(saved_cfg, cfg)))
    if state.epochs != spec.epochs:
        problems.append(f"run planned {state.epochs} epochs, not {spec.epochs}")
    if state.world_size != info.world_size:
        problems.append(f"trained by {state.world_size} processes, not {info.world_size}")
    changed = config_diff(state.train, train_cfg, ignore=("num_workers",))  # workers may change
    if changed:
        problems.append("train config differs: " + ", ".join(changed))
    if problems:
        raise MsdnetError(folder, "cannot resume: " + "; ".join(problems))
    load_weights(model, folder / "model.safetensors")
    load_training_state(folder, optimizer, scheduler, ema)
    return state


@contextmanager
def deterministic_algorithms() -> Iterator[None]:
    """Deterministic torch kernels (e.g. the index-accumulate backward of the rulebook gather)
    while training, so that equal seeds give equal weights; restored afterwards.

    Unfilled memory is left unfilled (filling it with NaN, torch's default in this mode, costs time
    on every step).
    """
    saved = (
        torch.are_deterministic_algorithms_enabled(),
        torch.is_deterministic_algorithms_warn_only_enabled(),
        torch.utils.deterministic.fill_uninitialized_memory,
    )
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.utils.deterministic.fill_uninitialized_memory = False
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(saved[0], warn_only=saved[1])
        torch.utils.deterministic.fill_uninitialized_memory = saved[2]


@deterministic_algorithms()
def train(
    model: torch.nn.Module,
    cfg: ModelConfig,
    train_cfg: TrainConfig,
    train_set: Dataset,
    val_set: Dataset,
    spec: RunSpec,
    collate_fn: Callable[[Sequence[Any]], Any],
    info: DistInfo | None = None,
    metrics_fn: MetricsFn | None = None,
) -> CheckpointState:
    """Train ``model`` (anything with ``losses(batch) -> {"loss": total, term: value}``).

    Returns the state after the last epoch run; writes checkpoints and the log on rank 0.
    Raises NonFiniteLoss (all ranks) at the first NaN / Inf term.
    """
    run = _Run(model, cfg, train_cfg, train_set, spec, collate_fn, info or DistInfo())
    state, log = run.state, run.log
    if log:
        log.write("start", kind=spec.kind, epoch=state.epoch, step=state.step,
                  epochs=spec.epochs, world_size=run.info.world_size, resume=spec.resume,
                  train_frames=len(train_set), val_frames=len(val_set))  # fmt: skip
    done_here = 0
    try:
        while state.epoch < spec.epochs and (spec.stop_after is None or done_here < spec.stop_after):
            t0 = time.perf_counter()
            record = run.epoch()
            with run.ema_weights():  # validation scores the EMA weights when there is one
                record.update(evaluate(model, val_set, collate_fn, train_cfg, run.info, run.device,
                                       metrics_fn, spec.metric_frames))  # fmt: skip
            record.update(occupancy_scores(record))
            record["lr"] = run.scheduler.get_last_lr()[0]
            record["seconds"] = round(time.perf_counter() - t0, 3)
            state.epoch += 1
            state.batch_in_epoch = 0
            state.history.append(record)
            val = record.get("val_loss", math.inf)
            best = state.best_val_loss is None or val < state.best_val_loss
            if best:
                state.best_val_loss = val
            run.save("last")
            if best:
                with run.ema_weights():  # best/ holds the weights that were scored
                    run.save("best")
            if log:
                log.write("epoch", best=best, **record)
            done_here += 1
    except NonFiniteLoss as err:
        if log:
            log.write("stop", epoch=state.epoch, step=state.step, finished=False, error=str(err))
        raise
    if log:
        log.write("stop", epoch=state.epoch, step=state.step, finished=state.epoch >= spec.epochs)
    return state


class _Run:
    """The objects of one training run: optimizer, schedule, sampler, loader, state, log."""

    def __init__(
        self,
        model: torch.nn.Module,
        cfg: ModelConfig,
        train_cfg: TrainConfig,
        train_set: Dataset,
        spec: RunSpec,
        collate_fn: Callable[[Sequence[Any]], Any],
        info: DistInfo,
    ) -> None:
        self.model, self.cfg, self.train_cfg, self.spec, self.info = model, cfg, train_cfg, spec, info
        self.device = torch.device(spec.device)
        model.to(self.device)
        self.params = [p for p in model.parameters() if p.requires_grad]  # not a frozen teacher
        # EMA of the trainable weights by name (TrainConfig.ema_decay; None when off)
        self.ema: dict[str, torch.Tensor] | None = None
        if train_cfg.ema_decay > 0:
            named = model.named_parameters()
            self.ema = {n: p.detach().clone() for n, p in named if p.requires_grad}
        augments = getattr(train_set, "augments", False)  # a dataset with (epoch, i) keys
        self.sampler = EpochSampler(train_set, info, train_cfg.seed, with_epoch=augments)
        steps_per_epoch = math.ceil(len(self.sampler) / train_cfg.batch_size)
        self.optimizer = torch.optim.Adam(self.params, lr=train_cfg.lr, weight_decay=train_cfg.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.OneCycleLR(
            self.optimizer, max_lr=train_cfg.lr, total_steps=max(1, spec.epochs * steps_per_epoch)
        )
        if spec.resume:
            self.state = _resume_state(
                spec, cfg, train_cfg, info, model, self.optimizer, self.scheduler, self.ema
            )
        else:
            self.state = CheckpointState(kind=spec.kind, train=train_cfg, epochs=spec.epochs,
                                         teacher=spec.teacher, dataset=spec.dataset,
                                         world_size=info.world_size, init=spec.init)  # fmt: skip
        self.loader = DataLoader(
            train_set,
            batch_size=train_cfg.batch_size,
            sampler=self.sampler,
            collate_fn=collate_fn,
            num_workers=train_cfg.num_workers,
            persistent_workers=train_cfg.num_workers > 0,  # workers keep their frame caches
        )
        self.net = wrap_for_training(model, info)
        self.log = JsonLog(spec.out / "log.jsonl") if info.is_main else None

    def save(self, folder: str) -> None:
        """Checkpoint to ``out/<folder>`` (rank 0 only)."""
        if self.info.is_main:
            save_checkpoint(self.spec.out / folder, self.model, self.cfg, self.state,
                            self.optimizer, self.scheduler, self.ema)  # fmt: skip

    @torch.no_grad()
    def update_ema(self) -> None:
        """ema <- decay * ema + (1 - decay) * weights, after every optimizer step."""
        if self.ema is None:
            return
        weight = 1.0 - self.train_cfg.ema_decay
        for name, p in self.model.named_parameters():
            if name in self.ema:
                self.ema[name].lerp_(p.detach(), weight)

    @contextmanager
    def ema_weights(self) -> Iterator[None]:
        """The model holds the EMA weights inside the block (the raw ones are put back after);
        a no-op without EMA."""
        if self.ema is None:
            yield
            return
        params = dict(self.model.named_parameters())
        raw = {n: params[n].detach().clone() for n in self.ema}
        with torch.no_grad():
            for n, v in self.ema.items():
                params[n].copy_(v)
        try:
            yield
        finally:
            with torch.no_grad():
                for n, v in raw.items():
                    params[n].copy_(v)

    def epoch(self) -> dict[str, Any]:
        """One (possibly resumed) epoch of steps -> {"epoch", "step", "train_<term>": mean}.

        After a mid-epoch resume the means cover the batches run since the resume.
        """
        state, spec, bs = self.state, self.spec, self.train_cfg.batch_size
        self.sampler.set_position(state.epoch, state.batch_in_epoch * bs)
        self.model.train()
        sums: dict[str, float] = {}
        seen = 0
        bar = tqdm(
            self.loader,
            total=math.ceil((len(self.sampler) + self.sampler.skip) / bs),
            initial=state.batch_in_epoch,
            desc=f"{spec.kind} epoch {state.epoch + 1}/{spec.epochs}",
            disable=not self.info.is_main,
            dynamic_ncols=True,
        )
        for batch in bar:
            reseed(self.train_cfg.seed, self.info.rank, state.step)
            batch = _to_device(batch, self.device)
            losses = self.net(batch)
            _check_finite(losses, state, self.info)
            self.optimizer.zero_grad(set_to_none=True)
            losses["loss"].backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(self.params, self.train_cfg.grad_clip)
            self.optimizer.step()
            self.update_ema()
            self.scheduler.step()
            state.step += 1
            state.batch_in_epoch += 1
            n = _batch_size(batch)
            seen += n
            for k, v in losses.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach()) * n
            loss = float(losses["loss"].detach())
            lr = self.scheduler.get_last_lr()[0]
            bar.set_postfix(loss=f"{loss:.4g}", lr=f"{lr:.2e}")
            if self.log and spec.log_every and state.step % spec.log_every == 0:
                self.log.write("step", epoch=state.epoch + 1, step=state.step, loss=loss,
                               grad_norm=float(grad_norm), lr=lr)  # fmt: skip
            if spec.save_every and state.step % spec.save_every == 0:
                self.save("last")
        bar.close()
        record: dict[str, Any] = {"epoch": state.epoch + 1, "step": state.step}
        record.update({f"train_{k}": v for k, v in _reduce_means(sums, seen, self.info).items()})
        return record
