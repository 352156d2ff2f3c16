"""The dense reconstruction head with fixed-statistics norms everywhere below 1/8, whose
coarse-to-fine graph computes the 1/4 level only near the 1/8 voxels that see occupancy
(``ModelConfig.head_kind`` "gated8"; retrained from a student by ``training.recipe.retrain_gated8``).

Same layers and contract as :class:`~msdnet.training.nn.head_gated.GatedReconHead`, with three
norms fixed instead of one, and a 1/8 occupancy branch (a 1x1x1 conv, the 1/8 gate):

    norm                                  dense head          gated               gated8
    before the 1/4 conv (up-sampled 1/8)  volume GroupNorm    volume              volume (exact:
                                                                                  1/8 is 1,200 voxels)
    after the 1/4 conv                    volume              volume              fixed
    before the 1/2 conv (up-sampled 1/4)  volume              volume (exact)      fixed
    after the 1/2 conv                    volume              fixed               fixed

So every layer below 1/8 is a function of a voxel's 3x3x3 neighbourhood, and :meth:`sparse` grows
the occupied set coarse to fine, giving exactly the dense values where it computes. The gate rule
(what a voxel must pass to be computed):

    1/8        dense (lite: 1,200 voxels) -> x8, occupancy occ8; near8 = the largest occ8 in each
               1/8 voxel's 3x3x3 neighbourhood; P8+ = near8 > gate (the 1/8 voxels above the
               gate grown by one 1/8 voxel: a 1/8 voxel the gate misses is still computed when a
               neighbour passes)
    1/4 input  the up-sampled 1/8 volume, GroupNorm, ReLU: dense (lite: 8,000 rows of a 1x1x1
               map; the 3x3x3 conv after it is what costs)
    1/4 conv   per 1/4 voxel of C = the children of P8+ grown by one 1/4 voxel: a gather of 27
               neighbour rows + one matmul, fixed norm, ReLU -> x4, occ4; P4 = the children of
               P8+ with occ4 > gate, P4+ = P4 grown by one (inside C, so its x4 was computed)
    1/2, full  as ``GatedReconHead``: the children of P4+ up-sampled (fixed norm, ReLU), the 1/2
               conv per child of P4, the full scale under the 1/2 voxels with occ2 > gate

A kept 1/2 voxel so has occ2, its parent's occ4 and its grandparent's near8 all above the gate;
its gate occupancy is the smallest of the three (what ``export.gate`` calibrates on). The 1/8
term is a neighbourhood maximum, not the voxel's own occ8: one 1/8 voxel's low occupancy never
drops its block while a neighbour passes. With gate 0 every voxel is computed and the outputs
equal :meth:`packed`'s. Fixing a norm whose statistics the head was trained with moves its outputs
(docs/experiments.md), so this head is retrained on its source head's outputs after its norms are
calibrated.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from msdnet.training.config import ModelConfig
from msdnet.training.nn.head import rows
from msdnet.training.nn.head_gated import FixedGroupNorm, GatedReconHead, fixed_from


def near_occupancy(occ8: Tensor) -> Tensor:
    """occ8 (B, 1, D8, H8, W8) -> the largest value in each voxel's 3x3x3 neighbourhood (same
    shape): ``near > gate`` is the set ``occ8 > gate`` grown by one voxel."""
    return nn.functional.max_pool3d(occ8, 3, stride=1, padding=1)


class Gated8ReconHead(GatedReconHead):
    """GatedReconHead with every norm below 1/8 fixed, a 1/8 gate, and the coarse-to-fine graph
    of the module docstring."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__(cfg)
        c4 = self.c4
        self.post4[2][1] = fixed_from(self.post4[2][1])  # after the 1/4 conv
        self.post2[0] = fixed_from(self.post2[0])  # before the 1/2 conv
        self.occ8 = nn.Conv3d(c4, 1, 1)  # the 1/8 gate
        nn.init.constant_(self.occ8.bias, math.log(cfg.occupancy_prior / (1.0 - cfg.occupancy_prior)))
        _, h4, w4 = self.shapes[0]
        k = torch.arange(27)  # tap (kz * 3 + ky) * 3 + kx, as the 1/2 conv's
        taps = ((k // 9 - 1) * (h4 + 2) + (k // 3 % 3 - 1)) * (w4 + 2) + (k % 3 - 1)
        self.register_buffer("taps4", taps.reshape(1, 27), persistent=False)  # padded 1/4 volume

    def fixed_norms(self) -> list[FixedGroupNorm]:
        """The fixed norms in the order data reaches them (the order ``retrain_gated8`` calibrates)."""
        return [self.post4[2][1], self.post2[0], self.post2[2][1]]

    def levels(self, features: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """F^D (B, C, H8, W8) -> volumes x8 (B, c4, D8, H8, W8), x4 (B, c4, D4, H4, W4),
        x2 (B, c2, D2, H2, W2) (dense, for training)."""
        x8 = self._eighth(features)
        x4 = self.post4(self._crop(self.up4(x8), 0))
        return x8, x4, self.post2(self._crop(self.up2(x4), 1))

    def gate_volumes(self, features: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """F^D (1, C, H8, W8) -> the dense volumes the gate rule reads: near8 (D8, H8, W8), occ4
        (D4, H4, W4), occ2 (D2, H2, W2) (for tests and diagnostics; ``sparse`` computes them only
        where it needs them)."""
        x8, x4, x2 = self.levels(features)
        near8 = near_occupancy(torch.sigmoid(self.occ8(x8)))[0, 0]
        return near8, torch.sigmoid(self.occ[0](x4))[0, 0], torch.sigmoid(self.occ[1](x2))[0, 0]

    def sparse(self, features: Tensor, gate: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Coarse-to-fine inference, batch 1 (module docstring), with ``ReconHead.sparse``'s
        outputs; gate_occupancy (N,) = min(occ2, occ4, near8) of each kept 1/2 voxel."""
        d4, h4, w4 = self.shapes[0]
        c4, c2 = self.c4, self.up2.cout
        x8 = self._eighth(features)  # (1, c4, D8, H8, W8)
        d8, h8, w8 = x8.shape[2:]
        near8 = near_occupancy(torch.sigmoid(self.occ8(x8))).reshape(-1)  # (V8,)
        passed8 = (near8 > gate).float().reshape(d8, 1, h8, 1, w8, 1)  # P8+
        under = passed8.expand(d8, 2, h8, 2, w8, 2).reshape(1, 1, 2 * d8, 2 * h8, 2 * w8)
        under = under[:, :, :d4, :h4, :w4]  # (1, 1, D4, H4, W4) the children of P8+
        grown = nn.functional.max_pool3d(under, 3, stride=1, padding=1)  # grown by one 1/4 voxel
        q = torch.nonzero(grown.reshape(-1)).reshape(-1)  # (M4,) the 1/4 voxels computed, increasing
        z = torch.div(q, h4 * w4, rounding_mode="floor")
        y = torch.remainder(torch.div(q, w4, rounding_mode="floor"), h4)
        x = torch.remainder(q, w4)  # (M4,) each
        u4 = self.post4[:2](self._crop(self.up4(x8), 0))  # (1, c4, D4, H4, W4) GroupNorm, ReLU
        table = nn.functional.pad(u4, (1, 1, 1, 1, 1, 1)).reshape(c4, -1).t()  # (padded V4, c4)
        padded = ((z + 1) * (h4 + 2) + y + 1) * (w4 + 2) + x + 1  # (M4,)
        gathered = table.index_select(0, (padded.unsqueeze(1) + self.taps4).reshape(-1))
        conv = self.post4[2][0]
        w = conv.weight.permute(2, 3, 4, 1, 0).reshape(-1, c4)  # (27 * c4, c4)
        x4 = torch.relu(self.post4[2][1].on_rows(gathered.reshape(-1, w.shape[0]) @ w))  # (M4, c4)
        parent8 = (torch.div(z, 2, rounding_mode="floor") * h8 + torch.div(y, 2, rounding_mode="floor")) * w8
        parent8 = parent8 + torch.div(x, 2, rounding_mode="floor")  # (M4,) 1/8 parent
        # P4 needs occ4 > gate and a parent in P8+ (the grown rim of C has neither in general)
        occ4 = torch.minimum(torch.sigmoid(rows(self.occ[0], x4)).reshape(-1), near8.index_select(0, parent8))
        v4 = d4 * h4 * w4
        passed4 = torch.zeros(v4).scatter(0, q, (occ4 > gate).float())  # P4 (children of P8+ only)
        grown4 = nn.functional.max_pool3d(passed4.reshape(1, 1, d4, h4, w4), 3, stride=1, padding=1)
        par = torch.nonzero(grown4.reshape(-1)).reshape(-1)  # (K,) P4+, all computed
        row = torch.zeros(v4, dtype=torch.int64).scatter(0, q, torch.arange(q.shape[0]))  # 1/4 -> row
        r = row.index_select(0, par)  # (K,)
        is_p = passed4.index_select(0, par) > 0
        up = rows(self.up2.proj, x4.index_select(0, r)).reshape(-1, 8, c2)  # (K, child, c2)
        u = torch.relu(self.post2[0].on_rows(up))
        return self._half_level(par, is_p, u, occ4.index_select(0, r), gate)
