"""Fine-tune a gated head's 1/2 level to give the dense head's outputs (``calibrate_gated
--finetune ITERATIONS``; the fallback of the ninth cycle's rule in docs/training.md).

Fixing the statistics of the norm after the 1/2 conv (``head_gated``) moves every output below
it a little, frame by frame. This step retrains only the layers after the fixed norm's input so
that the gated head reproduces, on the student's own loop features of its fitted frames, what the
dense head it came from decodes there (distillation; the LiDAR targets are not read):

    trained   the 1/2 3x3x3 conv, the fixed norm's affine, the 1/2 occupancy branch (the gate),
              ``up1`` and ``full`` (the full-scale children); the 1/2 offsets, which the
              runtime does not decode, are left as they are
    frozen    everything up to the conv's input (the 1/8 and 1/4 levels, the up-sampling and the
              exact per-frame norm before the conv): cached once per frame
    loss      per frame: soft BCE of the full-scale occupancy logits to the dense head's
              occupancy + soft BCE of the 1/2 occupancy (the gate) to the dense head's
              + ``offset_weight`` x the L1 of the full-scale offsets in units of half a voxel,
              weighted by the dense occupancy

The loss is the mean over all frames, minimised by L-BFGS (deterministic; per-frame Adam steps
raised it: the gated head starts within a KL of 5e-5 of the dense one, below their noise). The
log gives the loss and the share of full-scale voxels whose decision at ``threshold`` differs
from the dense head's, before and after, so a fine-tune that does not help is seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from msdnet.training.head import ReconHead
from msdnet.training.head_gated import GatedReconHead
from msdnet.training.latent import LatentHead


@dataclass(frozen=True)
class FinetuneConfig:
    """How the 1/2 level is fine-tuned."""

    iterations: int = 60  # L-BFGS iterations (each one pass over the frames, more in line searches)
    offset_weight: float = 1.0  # weight of the offsets' L1 (units of half a voxel) in the loss
    gate_weight: float = 0.1  # weight of the 1/2 occupancy's BCE in the loss
    threshold: float = 0.5  # decision threshold of the logged disagreement


@dataclass(frozen=True)
class Target:
    """One frame: the frozen conv input and what the dense head gives."""

    conv_in: Tensor  # (1, c2, D2, H2, W2) ReLU(GroupNorm(up2(x4))), the 1/2 conv's input
    occ: Tensor  # (1, 8, D2, H2, W2) dense full-scale occupancy, packed children
    off: Tensor  # (1, 8, 3, D2, H2, W2) dense full-scale offsets, metres
    half_occ: Tensor  # (1, 1, D2, H2, W2) dense 1/2 occupancy


def targets(dense: LatentHead, features: list[Tensor]) -> list[Target]:
    """Per frame of ``features`` (normalised F^D (1, C, H8, W8)) its :class:`Target`. The conv's
    input is the dense head's: the gated head built from it (``calibrate_gated``) has the same
    layers and weights up to there, with the same exact per-frame norm."""
    d = dense._head
    assert isinstance(d, ReconHead)
    out = []
    with torch.no_grad():
        for z in features:
            x4 = d._quarter(dense._f(z))  # (1, c4, D4, H4, W4)
            conv_in = d.post2[:2](d._crop(d.up2(x4), 1))  # GroupNorm, ReLU: (1, c2, D2, H2, W2)
            x2 = d.post2[2:](conv_in)  # conv, GroupNorm, ReLU
            occ, off = d._packed_children(x2)
            out.append(Target(conv_in, occ, off, torch.sigmoid(d.occ[1](x2))))
    return out


def _outputs(head: GatedReconHead, conv_in: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """conv_in -> (full-scale logits (1, 8, D2, H2, W2), offsets (1, 8, 3, D2, H2, W2),
    1/2 occupancy logits (1, 1, D2, H2, W2)) through the trained layers."""
    x2 = head.post2[2:](conv_in)  # conv, fixed norm, ReLU
    y = head.full(torch.relu(head.up1(x2)))  # (1, 8 * 4, D2, H2, W2)
    b, _, d2, h2, w2 = y.shape
    y = y.reshape(b, 8, 4, d2, h2, w2)
    half = head.half_size_2.reshape(1, 1, 3, 1, 1, 1)
    return y[:, :, 0], torch.tanh(y[:, :, 1:]) * half, head.occ[1](x2)


def _loss(head: GatedReconHead, t: Target, cfg: FinetuneConfig) -> tuple[Tensor, Tensor]:
    """(loss, share of full-scale voxels decided otherwise than the dense head at cfg.threshold)."""
    bce = nn.functional.binary_cross_entropy_with_logits
    logits, off, half = _outputs(head, t.conv_in)
    scale = head.half_size_2.reshape(1, 1, 3, 1, 1, 1)
    l1 = ((off - t.off).abs() / scale).sum(2)  # (1, 8, D2, H2, W2) in half voxels
    loss = (
        bce(logits, t.occ)
        + cfg.gate_weight * bce(half, t.half_occ)
        + cfg.offset_weight * (l1 * t.occ).sum() / t.occ.sum().clamp_min(1.0)
    )
    logit_thr = float(np.log(cfg.threshold / (1.0 - cfg.threshold)))
    flips = ((logits > logit_thr) != (t.occ > cfg.threshold)).float().mean()
    return loss, flips.detach()


def _trained(head: GatedReconHead) -> list[nn.Parameter]:
    mods = [head.post2[2][0], head.fixed_norm(), head.occ[1], head.up1, head.full]
    return [p for m in mods for p in m.parameters()]


def finetune_level(
    gated: LatentHead, dense: LatentHead, features: list[Tensor], cfg: FinetuneConfig
) -> dict[str, float]:
    """Fine-tune ``gated``'s 1/2 level in place (module docstring); -> mean loss and
    disagreement over the frames before and after."""
    head = gated._head
    assert isinstance(head, GatedReconHead)
    data = targets(dense, features)

    def score() -> tuple[float, float]:
        with torch.no_grad():
            rows = [_loss(head, t, cfg) for t in data]
        return float(np.mean([r[0] for r in rows])), float(np.mean([r[1] for r in rows]))

    before = score()
    params = _trained(head)
    trained = {id(p) for p in params}
    was = {id(p): p.requires_grad for p in head.parameters()}
    for p in head.parameters():
        p.requires_grad_(id(p) in trained)
    opt = torch.optim.LBFGS(params, max_iter=cfg.iterations, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        total = torch.zeros(())
        for t in data:  # one frame's graph at a time: gradients accumulate
            loss = _loss(head, t, cfg)[0] / len(data)
            loss.backward()
            total += loss.detach()
        return total

    try:
        opt.step(closure)
    finally:
        for p in head.parameters():
            p.requires_grad_(was[id(p)])
    after = score()
    return {
        "loss_before": before[0],
        "loss_after": after[0],
        "flips_before": before[1],
        "flips_after": after[1],
    }
