"""Retrain a student's head as the gated8 head (``head_kind`` "gated8", ``training/nn/head_gated8.py``):
every norm below 1/8 fixed, so its coarse-to-fine graph stays sparse from 1/4 down. The source is a
student with the dense head or the gated head (``recipe.gated_head``; its 1/2 norm is already fixed
and stays as it is). The student's other weights do not change; the head learns to give what the
source head decodes (``recipe.gated8_distill``), on the student's own loop features of the fitted
frames:

1. **Calibrate.** The fixed norms the source does not already fix get the pooled statistics of
   their inputs over the fitted frames, in the order data reaches them (each behind the ones
   before it, already fixed), as ``recipe.gated_head`` does for its one norm. This alone moves the
   outputs (the log says how much).
2. **Retrain** every head weight with Adam, one frame a step, the frames in a seeded order, cosine
   learning rate, on ``gated8_distill.frame_loss``.
3. **Select.** After every epoch the loss and the share of full-scale voxels decided otherwise
   than the source head (at ``--threshold``) are measured on the selection slice (the last
   ``--holdout`` of the training range, never fitted); the epoch with the lowest slice loss is
   written to ``--out``. Validation is never read.
4. **Refit the gates** (``--refit-gates N``, on a checkpoint step 3 wrote): only the three gates
   (probes of the trunk's detached features; no dense output moves), Adam at ``--gates-lr``, the
   epoch with the lowest slice gates KL kept.

    python -m msdnet.training.recipe.retrain_gated8 CKPT --dataset astyx --data ROOT --steps 2 --out NEW
    python -m msdnet.training.recipe.retrain_gated8 NEW --dataset astyx --data ROOT --steps 2 \\
        --refit-gates 6 --gates-lr 1e-2 --out NEW2
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import click
import numpy as np
import torch

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.training.config import ModelConfig
from msdnet.training.data.datasets import make_splits
from msdnet.training.models.assembly import StudentModel, build_model
from msdnet.training.nn.head import ReconHead
from msdnet.training.nn.head_gated import FixedGroupNorm
from msdnet.training.nn.head_gated8 import Gated8ReconHead
from msdnet.training.recipe.checkpoint import CheckpointState, load_checkpoint, save_checkpoint
from msdnet.training.recipe.gated8_distill import (
    RetrainConfig,
    dense_targets,
    frame_loss,
    parts_line,
    refit_gates,
    score,
)
from msdnet.training.recipe.gated_head import loop_features, pooled_statistics

SOURCES = ("dense", "gated")  # head kinds a gated8 head is retrained from


def gated8_student(checkpoint: str | Path) -> tuple[StudentModel, StudentModel, ModelConfig, CheckpointState]:
    """(source student, the same student with the gated8 head (occ8 newly initialised), its config,
    CheckpointState)."""
    source, cfg, state = load_checkpoint(checkpoint)
    if state.kind != "student":
        raise MsdnetError(checkpoint, f"is a {state.kind} checkpoint; the gated8 head is for students")
    if cfg.head_kind not in SOURCES:
        raise MsdnetError(checkpoint, f"has head_kind {cfg.head_kind!r}; retrain from a dense or gated head")
    cfg = dataclasses.replace(cfg, head_kind="gated8")
    torch.manual_seed(0)
    model = build_model("student", cfg)
    missing, unexpected = model.load_state_dict(source.state_dict(), strict=False)
    if unexpected or any(".occ8." not in k for k in missing):
        raise MsdnetError(checkpoint, f"does not load into the gated8 head: {missing[:2]} {unexpected[:2]}")
    return source.eval(), model.eval(), cfg, state


def norms_to_calibrate(head: Gated8ReconHead, source: ReconHead) -> list[FixedGroupNorm]:
    """The gated8 head's fixed norms the source head had as volume norms (a gated source's 1/2
    norm is fixed already, its statistics folded in)."""
    fixed = {n for n, m in source.named_modules() if isinstance(m, FixedGroupNorm)}
    names = {id(m): n for n, m in head.named_modules()}
    return [m for m in head.fixed_norms() if names[id(m)] not in fixed]


@click.command()
@click.argument("checkpoint", type=click.Path(exists=True, file_okay=False))
@click.option("--dataset", required=True, help="Dataset the student was trained on.")
@click.option("--data", "root", required=True, type=click.Path(exists=True), help="Its root folder.")
@click.option("--out", required=True, type=click.Path(), help="New checkpoint folder (the best epoch).")
@click.option("--holdout", type=float, default=0.15, show_default=True, help="As msdnet-train: the slice.")
@click.option("--val-fraction", type=float, default=0.2, show_default=True, help="As msdnet-train.")
@click.option("--steps", type=int, default=None, help="DDIM steps of the loop features [the config's].")
@click.option("--epochs", type=int, default=RetrainConfig.epochs, show_default=True)
@click.option("--lr", type=float, default=RetrainConfig.lr, show_default=True)
@click.option("--gate-weight", type=float, default=RetrainConfig.gate_weight, show_default=True)
@click.option("--threshold", type=float, default=RetrainConfig.threshold, show_default=True)
@click.option("--max-frames", type=int, default=None, help="Smoke runs: the first N frames only.")
@click.option("--seed", type=int, default=0, show_default=True, help="Noise of the loop and frame order.")
@click.option("--threads", type=int, default=None, help="torch threads.")
@click.option(
    "--refit-gates",
    "gate_epochs",
    type=click.IntRange(min=0),
    default=0,
    help="CHECKPOINT is a gated8 run: fit only its gates for N epochs (no dense output moves).",
)
@click.option("--gates-lr", type=float, default=1e-2, show_default=True, help="Adam's rate of --refit-gates.")
@one_line_errors
def main(
    checkpoint: str,
    dataset: str,
    root: str,
    out: str,
    holdout: float,
    val_fraction: float,
    steps: int | None,
    epochs: int,
    lr: float,
    gate_weight: float,
    threshold: float,
    max_frames: int | None,
    seed: int,
    threads: int | None,
    gate_epochs: int,
    gates_lr: float,
) -> None:
    """Retrain CHECKPOINT's dense or gated head as the gated8 head (module docstring); write it to --out."""
    if threads:
        torch.set_num_threads(threads)
    cfg_r = RetrainConfig(epochs=epochs, lr=lr, gate_weight=gate_weight, threshold=threshold, seed=seed)
    if gate_epochs:
        model, cfg, state = load_checkpoint(checkpoint)
        if cfg.head_kind != "gated8" or not state.init:
            raise MsdnetError(checkpoint, "--refit-gates takes a gated8 checkpoint written by this command")
        source = load_checkpoint(state.init)[0].eval()
    else:
        source, model, cfg, state = gated8_student(checkpoint)
    fit, select = make_splits(dataset, root, cfg, val_fraction, max_frames=max_frames, holdout=holdout)
    if len(select) == 0:
        raise MsdnetError(root, "no selection slice: --holdout must leave frames out")
    z_fit = loop_features(source, [fit[i][0] for i in range(len(fit))], seed, steps)
    z_sel = loop_features(source, [select[i][0] for i in range(len(select))], seed + 1, steps)
    f, head, shead = model.head._f, model.head._head, source.head._head
    assert isinstance(head, Gated8ReconHead) and isinstance(shead, ReconHead)
    t_fit, t_sel = dense_targets(shead, z_fit, f), dense_targets(shead, z_sel, f)
    x_fit, x_sel = [f(z).detach() for z in z_fit], [f(z).detach() for z in z_sel]

    if gate_epochs:
        with torch.no_grad():
            lv_fit, lv_sel = [list(head.levels(x)) for x in x_fit], [list(head.levels(x)) for x in x_sel]
        fit_pairs, sel_pairs = list(zip(lv_fit, t_fit, strict=True)), list(zip(lv_sel, t_sel, strict=True))
        before, after = refit_gates(head, fit_pairs, sel_pairs, gate_epochs, gates_lr, seed)
        save_checkpoint(out, model, cfg, state)
        click.echo(
            f"{out}: gates refit, slice gates KL {before:.3e} -> {after:.3e}; other weights: {checkpoint}"
        )
        return
    click.echo(
        f"source head as gated8, uncalibrated: slice {parts_line(score(head, x_sel, t_sel, cfg_r)[1])}"
    )
    for i, norm in enumerate(norms_to_calibrate(head, shead)):
        mean, var = pooled_statistics(norm, lambda: [head.packed(x) for x in x_fit])
        norm.fold(mean, var)
        click.echo(f"fixed norm {i}: mean {np.round(mean.numpy(), 2)}, var {np.round(var.numpy(), 2)}")
    best = score(head, x_sel, t_sel, cfg_r)
    click.echo(f"epoch 0 (calibrated): slice loss {best[0]:.4f}: {parts_line(best[1])}")
    save_checkpoint(out, model, cfg, dataclasses.replace(state, init=str(checkpoint)))

    for p in head.parameters():
        p.requires_grad_(True)  # the student holds the head frozen
    opt = torch.optim.Adam(head.parameters(), lr=lr)
    total = epochs * len(x_fit)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.5 * (1.0 + math.cos(math.pi * s / total)))
    order = np.random.default_rng(seed)
    head.train()
    for epoch in range(1, epochs + 1):
        t0, losses = time.time(), []
        for i in order.permutation(len(x_fit)):
            loss, parts = frame_loss(head, x_fit[i], t_fit[i], cfg_r)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            losses.append(parts.numpy())
        head.eval()
        now = score(head, x_sel, t_sel, cfg_r)
        mark = ""
        if now[0] < best[0]:
            best, mark = now, " (best: written)"
            save_checkpoint(out, model, cfg, dataclasses.replace(state, init=str(checkpoint), epoch=epoch))
        head.train()
        click.echo(f"epoch {epoch} ({time.time() - t0:.0f} s): fit {parts_line(np.mean(losses, 0))}")
        click.echo(f"  slice loss {now[0]:.4f}: {parts_line(now[1])}{mark}")
    click.echo(f"{out}: gated8 head, slice loss {best[0]:.4f}: {parts_line(best[1])}")


if __name__ == "__main__":
    main()
