"""One side of ``msdnet-bench training-speed``: a process that trains one model step by step on
request and scores it on fixed held-out batches.

Two of these run side by side: "before" (the exact full-scale loss, OpenMP as the environment
left it) and "after" (the sparse full-scale rows, passive OpenMP threads). The OpenMP wait policy
is read once, when torch loads OpenMP, so each side is a process of its own: its environment is set
by the parent, and this module imports torch before anything of ``msdnet.training`` (which would
set the passive policy itself).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from pathlib import Path


@dataclass(frozen=True)
class Side:
    """What one side trains and how."""

    name: str  # "before" | "after"
    kind: str  # teacher | student
    dataset: str  # msdnet-train --dataset
    data: str  # dataset root
    preset: str  # model / train preset
    batch_size: int  # frames per step
    threads: int  # torch CPU threads
    full_scale_rate: float  # LossWeights.full_scale_rate (1 = exact, the "before" loss)
    steps: int  # distinct training batches drawn from the fitted frames (cycled)
    score_batches: int  # held-out batches (the selection slice) scored exactly
    seed: int  # weights and draws


def _config(side: Side):  # -> ModelConfig
    """The lite recipe's model config of docs/training.md for ``side.kind``."""
    from msdnet.training.config import MODEL_PRESETS
    from msdnet.training.data.datasets import config_for_dataset

    cfg = config_for_dataset(MODEL_PRESETS[side.preset], side.dataset)
    losses = replace(cfg.losses, occ_pos_weight=20.0, zeta=1.0, full_scale_rate=side.full_scale_rate)
    if side.kind == "student":  # F="--lambdas 1,0.01,0.01,10 --denoiser-grad joint --adapter-align 0 ..."
        losses = replace(
            losses, lambdas=(1.0, 0.01, 0.01, 10.0), denoiser_distill_grad=True, adapter_align=0.0
        )
        cfg = replace(
            cfg,
            denoiser_hidden=128,
            time_embed_dim=128,
            train_sample_steps=10,
            diffusion=replace(cfg.diffusion, sample_steps=10),
        )
    return replace(cfg, losses=losses)


def serve(side: Side, conn: Connection) -> None:
    """Answer ``("step", i)`` with the wall seconds of training step i (collate, forward, backward,
    Adam), ``("score", None)`` with the exact loss on the held-out batches, ``("stop", None)`` by
    returning. Sends ``("ready", omp_wait_policy)`` first, or ``("error", text)``."""
    import torch  # first: OpenMP reads this process's OMP_WAIT_POLICY now

    try:
        from msdnet.training.data.batch import collate
        from msdnet.training.data.datasets import make_splits
        from msdnet.training.models.assembly import build_model
        from msdnet.training.recipe.loop import deterministic_algorithms, reseed

        torch.set_num_threads(side.threads)
        cfg = _config(side)
        fit, select = make_splits(side.dataset, Path(side.data), cfg, holdout=0.15)
        torch.manual_seed(side.seed)
        teacher = build_model("teacher", cfg) if side.kind == "student" else None
        model = build_model(side.kind, cfg, teacher=teacher)
        params = [p for p in model.parameters() if p.requires_grad]
        opt = torch.optim.Adam(params, lr=1e-3)
        bs = side.batch_size
        fit_items = [fit[(0, i)] if fit.augments else fit[i] for i in range(min(len(fit), side.steps * bs))]
        score = [
            collate([select[i] for i in range(j * bs, (j + 1) * bs)], cfg=cfg)
            for j in range(side.score_batches)
        ]
    except Exception as err:  # noqa: BLE001 - reported to the parent in one line
        conn.send(("error", f"{type(err).__name__}: {err}"))
        return
    conn.send(("ready", os.environ.get("OMP_WAIT_POLICY", "")))
    with deterministic_algorithms():
        while True:
            what, arg = conn.recv()
            if what == "stop":
                return
            if what == "score":
                model.eval()
                with torch.no_grad():
                    reseed(side.seed, 0, 2**31 - 1)
                    conn.send(float(sum(float(model.losses(b)["loss"]) for b in score) / len(score)))
                model.train()
                continue
            i = int(arg) % max(1, len(fit_items) // bs)
            reseed(side.seed, 0, int(arg))
            start = time.perf_counter()
            batch = collate(fit_items[i * bs : (i + 1) * bs], cfg=cfg)
            losses = model.losses(batch)
            opt.zero_grad(set_to_none=True)
            losses["loss"].backward()
            torch.nn.utils.clip_grad_norm_(params, 10.0)
            opt.step()
            conn.send(time.perf_counter() - start)
