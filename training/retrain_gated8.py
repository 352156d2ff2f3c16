"""Retrain a dense student's head as the gated8 head (``head_kind`` "gated8",
``training/head_gated8.py``): every norm below 1/8 fixed, so its coarse-to-fine graph stays sparse
from 1/4 down. The student's other weights do not change; the head learns to give what the dense
head it came from decodes (distillation; the LiDAR targets are not read), on the student's own loop
features of the fitted frames:

1. **Calibrate.** The three fixed norms get the pooled statistics of their inputs over the fitted
   frames, in the order data reaches them (each behind the ones before it, already fixed), as
   ``calibrate_gated`` does for its one norm. This alone moves the outputs (the log says how much).
2. **Retrain** every head weight with Adam, one frame a step, the frames in a seeded order, cosine
   learning rate. Loss per frame, the dense head's outputs as targets:

       KL(full-scale occupancy, dense occupancy)                    (soft BCE less the targets'
                                                                     entropy; every voxel)
       + offset_weight x L1(full-scale offsets, dense), in half voxels, weighted by dense occupancy
       + gate_weight x sum over 1/8, 1/4, 1/2 of KL(that level's occupancy, the largest dense
         full-scale occupancy under each voxel)                     (what the gates must keep)

3. **Select.** After every epoch the same loss and the share of full-scale voxels decided
   otherwise than the dense head (at ``--threshold``) are measured on the selection slice (the
   last ``--holdout`` of the training range, never fitted); the epoch with the lowest slice loss
   is written to ``--out``. Validation is never read.

    python -m msdnet.training.retrain_gated8 CKPT --dataset astyx --data ROOT --steps 2 --out NEW

4. **Refit the gates** (``--refit-gates N``, on a checkpoint step 3 wrote): the three gates are
   probes of the trunk's detached features, so fitting them alone (Adam at ``--gates-lr``, the
   epoch with the lowest slice gates KL kept) moves no dense output, only which voxels the
   coarse-to-fine graph computes at a given recall. The new gates start from fresh weights, and the
   trunk's learning rate leaves them far from fitted.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import torch
from torch import Tensor, nn

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.training.calibrate_gated import loop_features, pooled_statistics
from msdnet.training.checkpoint import load_checkpoint, save_checkpoint
from msdnet.training.data import make_splits
from msdnet.training.head import ReconHead
from msdnet.training.head_gated8 import Gated8ReconHead
from msdnet.training.models import StudentModel, build_model


@dataclass(frozen=True)
class RetrainConfig:
    """How the gated8 head is retrained."""

    epochs: int = 10  # passes over the fitted frames
    lr: float = 1e-4  # Adam's peak learning rate (cosine to 0 over the run)
    offset_weight: float = 1.0  # weight of the full-scale offsets' L1 (units of half a voxel)
    gate_weight: float = 0.1  # weight of each level's gate BCE
    threshold: float = 0.5  # decision threshold of the logged disagreement
    seed: int = 0  # order of the frames


@dataclass(frozen=True)
class Target:
    """One frame's dense-head outputs (float16 to halve the cache)."""

    occ: Tensor  # (1, 8, D2, H2, W2) full-scale occupancy, packed children
    off: Tensor  # (1, 8, 3, D2, H2, W2) full-scale offsets, metres
    gates: tuple[Tensor, Tensor, Tensor]  # largest occupancy under each 1/8, 1/4, 1/2 voxel


def _pool_up(occ: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """occ (D, H, W) at one scale -> the largest of each coarser voxel's children (shape), the
    children beyond the fine grid (crops) counting as 0."""
    d, h, w = shape
    top = torch.zeros(2 * d, 2 * h, 2 * w)
    top[: occ.shape[0], : occ.shape[1], : occ.shape[2]] = occ
    return top.reshape(d, 2, h, 2, w, 2).amax((1, 3, 5))


def dense_targets(dense: ReconHead, features: list[Tensor], f: nn.Module) -> list[Target]:
    """Per frame of ``features`` (normalised F^D) the dense head's :class:`Target`; ``f``
    de-normalises (``LatentHead._f``)."""
    out = []
    with torch.no_grad():
        for z in features:
            x8 = dense._eighth(f(z))
            occ, off = dense._packed_children(dense._trunk(f(z))[1])  # (1, 8, D2, H2, W2), offsets
            g2 = occ[0].amax(0)  # (D2, H2, W2)
            g4 = _pool_up(g2, dense.shapes[0])
            g8 = _pool_up(g4, tuple(x8.shape[2:]))
            out.append(Target(occ.half(), off.half(), (g8.half(), g4.half(), g2.half())))
    return out


def _kl(logits: Tensor, target: Tensor) -> Tensor:
    """Mean KL divergence of Bernoulli(sigmoid(logits)) from Bernoulli(target): the soft BCE less
    the targets' own entropy, so 0 means the dense head's occupancy exactly (same gradient)."""
    t = target.clamp(1e-6, 1.0 - 1e-6)
    entropy = -(t * torch.log(t) + (1.0 - t) * torch.log1p(-t)).mean()
    return nn.functional.binary_cross_entropy_with_logits(logits, target) - entropy


def _loss(head: Gated8ReconHead, z: Tensor, t: Target, cfg: RetrainConfig) -> tuple[Tensor, Tensor]:
    """One frame: (loss, its parts [occupancy KL, offsets' L1, gates' KL, share of full-scale
    voxels decided otherwise than the dense head at cfg.threshold] detached)."""
    x8, x4, x2 = head.levels(z)
    y = head.full(torch.relu(head.up1(x2)))  # (1, 8 * 4, D2, H2, W2)
    b, _, d2, h2, w2 = y.shape
    y = y.reshape(b, 8, 4, d2, h2, w2)  # (1, child, [logit, dx, dy, dz], D2, H2, W2)
    scale = head.half_size_2.reshape(1, 1, 3, 1, 1, 1)
    logits, off = y[:, :, 0], torch.tanh(y[:, :, 1:]) * scale
    occ, t_off = t.occ.float(), t.off.float()
    l1 = ((off - t_off).abs() / scale).sum(2)  # (1, 8, D2, H2, W2) in half voxels
    # the gates are probes of the trunk's features: their loss does not move the trunk
    gate_logits = (head.occ8(x8.detach()), head.occ[0](x4.detach()), head.occ[1](x2.detach()))
    gates = sum(_kl(g[0, 0], tg.float()) for g, tg in zip(gate_logits, t.gates, strict=True))
    occ_kl = _kl(logits, occ)
    off_l1 = (l1 * occ).sum() / occ.sum().clamp_min(1.0)
    logit_thr = math.log(cfg.threshold / (1.0 - cfg.threshold))
    flips = ((logits > logit_thr) != (occ > cfg.threshold)).float().mean()
    parts = torch.stack([occ_kl, off_l1, gates, flips]).detach()
    return occ_kl + cfg.offset_weight * off_l1 + cfg.gate_weight * gates, parts


def score(
    head: Gated8ReconHead, zs: list[Tensor], ts: list[Target], cfg: RetrainConfig
) -> tuple[float, np.ndarray]:
    """Mean loss and mean parts (:func:`_loss`) over frames."""
    with torch.no_grad():
        r = [_loss(head, z, t, cfg) for z, t in zip(zs, ts, strict=True)]
    return float(np.mean([float(a) for a, _ in r])), torch.stack([b for _, b in r]).mean(0).numpy()


def _parts(p: np.ndarray) -> str:
    return f"occupancy KL {p[0]:.2e}, offsets {p[1]:.4f}, gates KL {p[2]:.2e}, decided otherwise {p[3]:.3%}"


def refit_gates(
    head: Gated8ReconHead,
    fit: list[tuple[list[Tensor], Target]],
    select: list[tuple[list[Tensor], Target]],
    epochs: int,
    lr: float,
    seed: int = 0,
) -> tuple[float, float]:
    """Fit only the three gates (1x1x1 probes on the trunk's detached x8, x4, x2: no dense output
    moves) to the gate targets, Adam one frame a step; keep the epoch with the lowest slice gates KL.
    fit / select: per frame (the trunk's [x8, x4, x2], Target). -> slice gates KL (before, after)."""
    probes = [head.occ8, head.occ[0], head.occ[1]]
    params = [p for m in probes for p in m.parameters()]
    for p in params:
        p.requires_grad_(True)  # the student holds the head frozen

    def kl(levels: list[Tensor], t: Target) -> Tensor:
        return sum(_kl(m(v)[0, 0], g.float()) for m, v, g in zip(probes, levels, t.gates, strict=True))

    def on_slice() -> float:
        with torch.no_grad():
            return float(np.mean([float(kl(v, t)) for v, t in select]))

    first = best = on_slice()
    kept = [p.detach().clone() for p in params]
    opt, order = torch.optim.Adam(params, lr=lr), np.random.default_rng(seed)
    for epoch in range(1, epochs + 1):
        for i in order.permutation(len(fit)):
            opt.zero_grad()
            kl(*fit[i]).backward()
            opt.step()
        now = on_slice()
        click.echo(f"gates epoch {epoch}: slice gates KL {now:.3e}" + (" (best)" if now < best else ""))
        if now < best:
            best, kept = now, [p.detach().clone() for p in params]
    with torch.no_grad():
        for p, k in zip(params, kept, strict=True):
            p.copy_(k)
    return first, best


def gated8_student(checkpoint: str | Path) -> tuple[StudentModel, StudentModel, object, object]:
    """(dense student, the same student with the gated8 head (occ8 newly initialised), its config,
    CheckpointState)."""
    dense, cfg, state = load_checkpoint(checkpoint)
    if state.kind != "student":
        raise MsdnetError(checkpoint, f"is a {state.kind} checkpoint; the gated8 head is for students")
    if cfg.head_kind != "dense":
        raise MsdnetError(checkpoint, f"has head_kind {cfg.head_kind!r}; retrain from a dense head")
    cfg = dataclasses.replace(cfg, head_kind="gated8")
    torch.manual_seed(0)
    model = build_model("student", cfg)
    missing, unexpected = model.load_state_dict(dense.state_dict(), strict=False)
    if unexpected or any(".occ8." not in k for k in missing):
        raise MsdnetError(checkpoint, f"does not load into the gated8 head: {missing[:2]} {unexpected[:2]}")
    return dense.eval(), model.eval(), cfg, state


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
    """Retrain CHECKPOINT's dense head as the gated8 head (module docstring); write it to --out."""
    if threads:
        torch.set_num_threads(threads)
    cfg_r = RetrainConfig(epochs=epochs, lr=lr, gate_weight=gate_weight, threshold=threshold, seed=seed)
    if gate_epochs:
        model, cfg, state = load_checkpoint(checkpoint)
        if cfg.head_kind != "gated8" or not state.init:
            raise MsdnetError(checkpoint, "--refit-gates takes a gated8 checkpoint written by this command")
        dense = load_checkpoint(state.init)[0].eval()
    else:
        dense, model, cfg, state = gated8_student(checkpoint)
    fit, select = make_splits(dataset, root, cfg, val_fraction, max_frames=max_frames, holdout=holdout)
    if len(select) == 0:
        raise MsdnetError(root, "no selection slice: --holdout must leave frames out")
    z_fit = loop_features(dense, [fit[i][0] for i in range(len(fit))], seed, steps)
    z_sel = loop_features(dense, [select[i][0] for i in range(len(select))], seed + 1, steps)
    f, head, dhead = model.head._f, model.head._head, dense.head._head
    assert isinstance(head, Gated8ReconHead) and isinstance(dhead, ReconHead)
    t_fit, t_sel = dense_targets(dhead, z_fit, f), dense_targets(dhead, z_sel, f)
    x_fit, x_sel = [f(z).detach() for z in z_fit], [f(z).detach() for z in z_sel]

    if gate_epochs:
        with torch.no_grad():
            lv_fit, lv_sel = [list(head.levels(x)) for x in x_fit], [list(head.levels(x)) for x in x_sel]
        before, after = refit_gates(
            head,
            list(zip(lv_fit, t_fit, strict=True)),
            list(zip(lv_sel, t_sel, strict=True)),
            gate_epochs,
            gates_lr,
        )
        save_checkpoint(out, model, cfg, state)
        click.echo(
            f"{out}: gates refit, slice gates KL {before:.3e} -> {after:.3e}; other weights: {checkpoint}"
        )
        return
    click.echo(f"dense head as gated8, statistics 0 / 1: slice {_parts(score(head, x_sel, t_sel, cfg_r)[1])}")
    for i, norm in enumerate(head.fixed_norms()):
        mean, var = pooled_statistics(norm, lambda: [head.packed(x) for x in x_fit])
        norm.fold(mean, var)
        click.echo(f"fixed norm {i}: mean {np.round(mean.numpy(), 2)}, var {np.round(var.numpy(), 2)}")
    best = score(head, x_sel, t_sel, cfg_r)
    click.echo(f"epoch 0 (calibrated): slice loss {best[0]:.4f}: {_parts(best[1])}")
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
            loss, parts = _loss(head, x_fit[i], t_fit[i], cfg_r)
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
        click.echo(f"epoch {epoch} ({time.time() - t0:.0f} s): fit {_parts(np.mean(losses, 0))}")
        click.echo(f"  slice loss {now[0]:.4f}: {_parts(now[1])}{mark}")
    click.echo(f"{out}: gated8 head, slice loss {best[0]:.4f}: {_parts(best[1])}")


if __name__ == "__main__":
    main()
