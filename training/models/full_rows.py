"""The full-scale part of Eq. 5-6 on a sparse set of voxels, unbiased: what a training step
computes of the head's finest level.

The head's full scale (lite: 20 x 160 x 160 = 512 k voxels a frame) costs a third of a teacher
step in torch, yet an Astyx LiDAR frame occupies about 2 k of those voxels. The exact loss sums
over every voxel; this module keeps

- every half-scale voxel under an occupied quarter-scale voxel (the surfaces and their
  neighbourhood: every occupied full-scale voxel and the empty ones beside it), weight 1;
- each other half-scale voxel (all eight children empty, far from every LiDAR point) with
  probability ``rate``, weight ``1 / rate``,

and the head computes the eight full-scale children of the kept half-scale voxels only (the rows
form of ``HeadOutputs._row_children``). Each term keeps its normaliser (Eq. 5: all N full-scale
voxels; Eq. 6: the occupied ones), so the loss and its gradient equal the dense ones in
expectation over the draw, and exactly at ``rate = 1``. The draw uses torch's global generator,
which the training loop reseeds before every step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

# child c = (dz * 2 + dy) * 2 + dx of a half-scale voxel -> (dz, dy, dx), the head's child order
_CHILD = torch.tensor([[c >> 2 & 1, c >> 1 & 1, c & 1] for c in range(8)])  # (8, 3) [dz, dy, dx]


@dataclass(frozen=True)
class FullRows:
    """The full-scale voxels one step scores, as the half-scale voxels whose children they are."""

    index: Tensor  # (N,) int64 kept half-scale voxels, linear in the flattened (B, D2, H2, W2)
    weight: Tensor  # (N,) float32: 1 near the surfaces, 1 / rate for the sampled far voxels
    occ: Tensor  # (N, 8) float32 {0, 1} full-scale occupancy target of each child
    off: Tensor  # (N, 8, 3) float32 metres [dx, dy, dz] target offsets of each child
    inside: Tensor  # (N, 8) float32: 1 where the child lies inside the full grid (crop)
    voxels: int  # B * D * H * W: the full-scale voxels Eq. 5 averages over
    occupied: Tensor  # () float32: occupied full-scale voxels, Eq. 6's count


def select_rows(targets: Sequence[tuple[Tensor, Tensor]], rate: float) -> FullRows:
    """targets: per scale 1/4, 1/2, 1 (occ (B, D, H, W), off (B, 3, D, H, W)) -> the rows to score.

    rate: in (0, 1], the share of far half-scale voxels drawn (1 keeps every voxel: exact).
    """
    if not 0.0 < rate <= 1.0:
        raise ValueError(f"rate must be in (0, 1], got {rate}")
    occ4, (occ2, _), (occ1, off1) = targets[0][0], targets[1], targets[2]
    b, d2, h2, w2 = occ2.shape
    _, d1, h1, w1 = occ1.shape
    near = occ4 > 0.5  # (B, D4, H4, W4) -> its 8 half-scale children, cropped to the 1/2 grid
    near = near.repeat_interleave(2, 1).repeat_interleave(2, 2).repeat_interleave(2, 3)[:, :d2, :h2, :w2]
    near = near.reshape(-1)  # (B * D2 * H2 * W2,)
    keep = near | (torch.rand(near.shape, device=near.device) < rate) if rate < 1.0 else torch.ones_like(near)
    index = torch.nonzero(keep).reshape(-1)  # (N,) increasing
    weight = torch.where(near[index], 1.0, 1.0 / rate).to(occ1.dtype)  # (N,)
    x2, rest = torch.remainder(index, w2), torch.div(index, w2, rounding_mode="floor")
    y2, rest = torch.remainder(rest, h2), torch.div(rest, h2, rounding_mode="floor")
    z2, bb = torch.remainder(rest, d2), torch.div(rest, d2, rounding_mode="floor")  # (N,) each
    child = _CHILD.to(index.device)
    z = z2.unsqueeze(1) * 2 + child[:, 0]  # (N, 8) full-scale coordinates of each child
    y = y2.unsqueeze(1) * 2 + child[:, 1]
    x = x2.unsqueeze(1) * 2 + child[:, 2]
    inside = (z < d1) & (y < h1) & (x < w1)  # (N, 8) the crop of the full scale
    flat = ((bb.unsqueeze(1) * d1 + z.clamp_max(d1 - 1)) * h1 + y.clamp_max(h1 - 1)) * w1 + x.clamp_max(
        w1 - 1
    )
    inside_f = inside.to(occ1.dtype)
    occ = occ1.reshape(-1)[flat] * inside_f  # (N, 8)
    off = off1.permute(0, 2, 3, 4, 1).reshape(-1, 3)[flat.reshape(-1)].reshape(-1, 8, 3)  # (N, 8, 3)
    return FullRows(index, weight, occ, off, inside_f, b * d1 * h1 * w1, occ1.sum())


def rows_loss(logits: Tensor, offsets: Tensor, rows: FullRows, pos_weight: float) -> tuple[Tensor, Tensor]:
    """Eq. 5 and Eq. 6 at full scale from the rows form: logits (N, 8), offsets (N, 8, 3) metres
    -> (occupancy BCE averaged over every full-scale voxel, offset L1 over the occupied ones)."""
    w = rows.weight.unsqueeze(1) * rows.inside  # (N, 8)
    pw = logits.new_tensor(pos_weight) if pos_weight != 1.0 else None
    bce = F.binary_cross_entropy_with_logits(logits, rows.occ, weight=w, pos_weight=pw, reduction="sum")
    l1 = ((offsets - rows.off).abs() * rows.occ.unsqueeze(2)).sum()
    return bce / rows.voxels, l1 / rows.occupied.clamp_min(1.0)
