"""What ``retrain_gated8`` fits the gated8 head to: its source head's outputs (distillation; no
LiDAR target is read), and the refit of the three gates alone.

Loss per frame, the source head's outputs as targets:

    KL(full-scale occupancy, source occupancy)                       (soft BCE less the targets'
                                                                      entropy; every voxel)
    + offset_weight x L1(full-scale offsets, source), in half voxels, weighted by source occupancy
    + gate_weight x sum over 1/8, 1/4, 1/2 of KL(that level's occupancy, the largest source
      full-scale occupancy under each voxel)                         (what the gates must keep)

The gates are probes of the trunk's detached features: their terms move no trunk weight.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import click
import numpy as np
import torch
from torch import Tensor, nn

from msdnet.training.nn.head import ReconHead
from msdnet.training.nn.head_gated8 import Gated8ReconHead


@dataclass(frozen=True)
class RetrainConfig:
    """How the gated8 head is retrained."""

    epochs: int = 10  # passes over the fitted frames
    lr: float = 1e-4  # Adam's peak learning rate (cosine to 0 over the run)
    offset_weight: float = 1.0  # weight of the full-scale offsets' L1 (units of half a voxel)
    gate_weight: float = 0.1  # weight of each level's gate KL
    threshold: float = 0.5  # decision threshold of the logged disagreement
    seed: int = 0  # order of the frames


@dataclass(frozen=True)
class Target:
    """One frame's source-head outputs (float16 to halve the cache)."""

    occ: Tensor  # (1, 8, D2, H2, W2) full-scale occupancy, packed children
    off: Tensor  # (1, 8, 3, D2, H2, W2) full-scale offsets, metres
    gates: tuple[Tensor, Tensor, Tensor]  # (D8, H8, W8), (D4, ...), (D2, ...): largest occ under each


def pool_up(occ: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """occ (D, H, W) at one scale -> (shape) the largest of each coarser voxel's children, the
    children beyond the fine grid (crops) counting as 0."""
    d, h, w = shape
    top = torch.zeros(2 * d, 2 * h, 2 * w)
    top[: occ.shape[0], : occ.shape[1], : occ.shape[2]] = occ
    return top.reshape(d, 2, h, 2, w, 2).amax((1, 3, 5))


def dense_targets(source: ReconHead, features: list[Tensor], f: Callable[[Tensor], Tensor]) -> list[Target]:
    """Per frame of ``features`` (normalised F^D (1, C, H8, W8)) the source head's packed outputs
    as a :class:`Target`; ``f`` de-normalises (``LatentHead._f``)."""
    out = []
    with torch.no_grad():
        for z in features:
            x8 = source._eighth(f(z))
            occ, off = source._packed_children(source._trunk(f(z))[1])  # (1, 8, D2, H2, W2), offsets
            g2 = occ[0].amax(0)  # (D2, H2, W2)
            g4 = pool_up(g2, source.shapes[0])
            g8 = pool_up(g4, tuple(x8.shape[2:]))
            out.append(Target(occ.half(), off.half(), (g8.half(), g4.half(), g2.half())))
    return out


def kl(logits: Tensor, target: Tensor) -> Tensor:
    """Mean KL divergence of Bernoulli(sigmoid(logits)) from Bernoulli(target), same shapes: the
    soft BCE less the targets' own entropy, so 0 means the target exactly (same gradient)."""
    t = target.clamp(1e-6, 1.0 - 1e-6)
    entropy = -(t * torch.log(t) + (1.0 - t) * torch.log1p(-t)).mean()
    return nn.functional.binary_cross_entropy_with_logits(logits, target) - entropy


def frame_loss(head: Gated8ReconHead, z: Tensor, t: Target, cfg: RetrainConfig) -> tuple[Tensor, Tensor]:
    """One frame z (1, C, H8, W8): (loss, its parts (4,) [occupancy KL, offsets' L1, gates' KL,
    share of full-scale voxels decided otherwise than the source at cfg.threshold] detached)."""
    x8, x4, x2 = head.levels(z)
    y = head.full(torch.relu(head.up1(x2)))  # (1, 8 * 4, D2, H2, W2)
    b, _, d2, h2, w2 = y.shape
    y = y.reshape(b, 8, 4, d2, h2, w2)  # (1, child, [logit, dx, dy, dz], D2, H2, W2)
    scale = head.half_size_2.reshape(1, 1, 3, 1, 1, 1)
    logits, off = y[:, :, 0], torch.tanh(y[:, :, 1:]) * scale
    occ, t_off = t.occ.float(), t.off.float()
    l1 = ((off - t_off).abs() / scale).sum(2)  # (1, 8, D2, H2, W2) in half voxels
    gate_logits = (head.occ8(x8.detach()), head.occ[0](x4.detach()), head.occ[1](x2.detach()))
    gates = sum(kl(g[0, 0], tg.float()) for g, tg in zip(gate_logits, t.gates, strict=True))
    occ_kl = kl(logits, occ)
    off_l1 = (l1 * occ).sum() / occ.sum().clamp_min(1.0)
    logit_thr = math.log(cfg.threshold / (1.0 - cfg.threshold))
    flips = ((logits > logit_thr) != (occ > cfg.threshold)).float().mean()
    parts = torch.stack([occ_kl, off_l1, gates, flips]).detach()
    return occ_kl + cfg.offset_weight * off_l1 + cfg.gate_weight * gates, parts


def score(
    head: Gated8ReconHead, zs: list[Tensor], ts: list[Target], cfg: RetrainConfig
) -> tuple[float, np.ndarray]:
    """Mean loss and mean parts (4,) (:func:`frame_loss`) over frames."""
    with torch.no_grad():
        r = [frame_loss(head, z, t, cfg) for z, t in zip(zs, ts, strict=True)]
    return float(np.mean([float(a) for a, _ in r])), torch.stack([b for _, b in r]).mean(0).numpy()


def parts_line(p: np.ndarray) -> str:
    """One log line of :func:`score`'s parts."""
    return f"occupancy KL {p[0]:.2e}, offsets {p[1]:.4f}, gates KL {p[2]:.2e}, decided otherwise {p[3]:.3%}"


Levels = list[Tensor]  # the trunk's [x8, x4, x2] of one frame


def refit_gates(
    head: Gated8ReconHead,
    fit: list[tuple[Levels, Target]],
    select: list[tuple[Levels, Target]],
    epochs: int,
    lr: float,
    seed: int = 0,
) -> tuple[float, float]:
    """Fit only the three gates (1x1x1 probes on the trunk's detached x8, x4, x2: no dense output
    moves) to the gate targets, Adam one frame a step; keep the epoch with the lowest slice gates KL.
    fit / select: per frame (levels, Target). -> slice gates KL (before, after)."""
    probes = [head.occ8, head.occ[0], head.occ[1]]
    params = [p for m in probes for p in m.parameters()]
    for p in params:
        p.requires_grad_(True)  # the student holds the head frozen

    def gates_kl(levels: Levels, t: Target) -> Tensor:
        return sum(kl(m(v)[0, 0], g.float()) for m, v, g in zip(probes, levels, t.gates, strict=True))

    def on_slice() -> float:
        with torch.no_grad():
            return float(np.mean([float(gates_kl(v, t)) for v, t in select]))

    first = best = on_slice()
    kept = [p.detach().clone() for p in params]
    opt, order = torch.optim.Adam(params, lr=lr), np.random.default_rng(seed)
    for epoch in range(1, epochs + 1):
        for i in order.permutation(len(fit)):
            opt.zero_grad()
            gates_kl(*fit[i]).backward()
            opt.step()
        now = on_slice()
        click.echo(f"gates epoch {epoch}: slice gates KL {now:.3e}" + (" (best)" if now < best else ""))
        if now < best:
            best, kept = now, [p.detach().clone() for p in params]
    with torch.no_grad():
        for p, k in zip(params, kept, strict=True):
            p.copy_(k)
    return first, best
