"""Loss terms of MSDNet (Eq. 5-8, 10, 14, 15) and R2LDM (its Eq. 4), each defined once.

Conventions: occupancy predictions arrive as logits (the BCE is computed from logits for
numerical stability; it is the same function of ``M = sigmoid(logit)`` as Eq. 5); offsets in
metres, channels [dx, dy, dz]; BEV features (B, C, H, W); masks (B, H, W) bool.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.nn import Module

from msdnet.training.config import LossWeights
from msdnet.training.models.full_rows import FullRows, rows_loss, select_rows

SCALE_NAMES = ("s4", "s2", "s1")  # scales 1/4, 1/2, 1 in head / target order


def occupancy_bce(logits: Tensor, target: Tensor, pos_weight: float = 1.0) -> Tensor:
    """MSDNet Eq. 5: ``-1/N sum_i [w M^_i log M_i + (1 - M^_i) log(1 - M_i)]``, M = sigmoid(logits).

    logits: (B, D, H, W) or any shape; target: same shape, {0, 1}. Mean over all N voxels.
    ``w = pos_weight`` weights the occupied voxels; the paper's loss is ``w = 1``.
    """
    if pos_weight == 1.0:
        return F.binary_cross_entropy_with_logits(logits, target, reduction="mean")
    w = logits.new_tensor(pos_weight)
    return F.binary_cross_entropy_with_logits(logits, target, reduction="mean", pos_weight=w)


def offset_l1(offsets: Tensor, target_offsets: Tensor, occupancy: Tensor) -> Tensor:
    """MSDNet Eq. 6: ``1/N_o sum_{occupied i} ||(dP_i + C_i) - P^_i||_1``.

    With target offset ``P^_i - C_i`` this is the L1 norm (sum over x, y, z) of offset error,
    averaged over the N_o occupied voxels. offsets, target_offsets: (B, 3, D, H, W) metres;
    occupancy: (B, D, H, W) {0, 1}. Zero (with a graph) when no voxel is occupied.
    """
    occ = occupancy.unsqueeze(1)  # (B, 1, D, H, W)
    err = ((offsets - target_offsets).abs() * occ).sum()
    return err / occupancy.sum().clamp_min(1.0)


def reconstruction_loss(
    preds: Sequence[tuple[Tensor, Tensor]],
    targets: Sequence[tuple[Tensor, Tensor]],
    weights: LossWeights,
    full_rows: FullRows | None = None,
) -> dict[str, Tensor]:
    """MSDNet Eq. 7: ``sum_s rho L_occ^(s) + sum_s zeta L_off^(s)`` over scales 1/4, 1/2, 1.

    preds: per scale (occupancy logits (B, 1, D, H, W), offsets (B, 3, D, H, W));
    targets: per scale (occ (B, D, H, W), off (B, 3, D, H, W)).
    full_rows: the full scale's preds are in the rows form (logits (N, 8), offsets (N, 8, 3)) on
    these voxels, scored unbiasedly (training/models/full_rows.py).
    Returns {"recon": total, "occ_s4", "off_s4", "occ_s2", "off_s2", "occ_s1", "off_s1"}.
    """
    out: dict[str, Tensor] = {}
    total = preds[0][0].new_zeros(())
    for name, (logits, off), (occ_t, off_t) in zip(SCALE_NAMES, preds, targets, strict=True):
        if name == SCALE_NAMES[-1] and full_rows is not None:
            l_occ, l_off = rows_loss(logits, off, full_rows, weights.occ_pos_weight)
        else:
            l_occ = occupancy_bce(logits.squeeze(1), occ_t, weights.occ_pos_weight)
            l_off = offset_l1(off, off_t, occ_t)
        out[f"occ_{name}"] = l_occ
        out[f"off_{name}"] = l_off
        total = total + weights.rho * l_occ + weights.zeta * l_off
    return {"recon": total, **out}


def feature_distillation(
    student: Tensor, teacher: Tensor, nonempty: Tensor, alpha: float, gamma: float
) -> Tensor:
    """MSDNet Eq. 8 (F^R) and Eq. 14 (F^D):
    ``alpha E_{i in Omega_ne} ||F_l^D(i) - F_r(i)||_2 + gamma E_{i in Omega_e} ||...||_2``.

    student, teacher: (B, C, H, W); the L2 norm runs over channels per BEV cell;
    nonempty: (B, H, W) bool, Omega_ne (its complement is Omega_e). Each expectation is the mean
    over its set across the batch; an empty set contributes 0.
    """
    dist = torch.linalg.vector_norm(teacher - student, ord=2, dim=1)  # (B, H, W)
    ne = nonempty.to(dist.dtype)
    e = 1.0 - ne
    mean_ne = (dist * ne).sum() / ne.sum().clamp_min(1.0)
    mean_e = (dist * e).sum() / e.sum().clamp_min(1.0)
    return alpha * mean_ne + gamma * mean_e


def eps_loss(eps_pred: Tensor, eps: Tensor) -> Tensor:
    """MSDNet Eq. 10 and R2LDM's L2 eps-prediction loss: ``E ||eps - Phi(x_t, t)||_2^2``,
    taken as the mean squared error over all elements (the DDPM convention)."""
    return F.mse_loss(eps_pred, eps, reduction="mean")


def student_total(
    recon: Tensor, distill_rec: Tensor, distill_diff: Tensor, diff: Tensor, weights: LossWeights
) -> Tensor:
    """MSDNet Eq. 15: ``l1 L_recon + l2 L_distill^rec + l3 L_distill^diff + l4 L_diff``."""
    l1, l2, l3, l4 = weights.lambdas
    return l1 * recon + l2 * distill_rec + l3 * distill_diff + l4 * diff


def head_loss(head: Module, features: Tensor, targets: Sequence[tuple[Tensor, Tensor]], weights: LossWeights,
              training: bool) -> dict[str, Tensor]:  # fmt: skip
    """Eq. 7 of ``head`` on ``features``: while training with ``weights.full_scale_rate`` < 1 the
    full scale on the rows :func:`~msdnet.training.models.full_rows.select_rows` draws, else dense
    (validation scores are exact)."""
    if training and weights.full_scale_rate < 1.0:
        rows = select_rows(targets, weights.full_scale_rate)
        return reconstruction_loss(head.multi_scale(features, rows.index), targets, weights, rows)
    return reconstruction_loss(head.multi_scale(features), targets, weights)
