"""A reconstruction head that stays sparse below its 1/4 level (``ModelConfig.head_kind``
"sparse"): the same contract as :class:`~msdnet.training.nn.head.ReconHead` (multi-scale logits and
offsets for Eq. 5-7, the packed full scale of ``recon_head.onnx``, the coarse-to-fine
``recon_head_sparse.onnx``), but only the 1/8 and 1/4 levels (small volumes) mix neighbours.

    F^D (B, C, H8, W8) -> 1x1 conv to c8 * D8 channels -> re-read as (B, c8, D8, H8, W8)
      -> two 3x3x3 conv + GroupNorm + ReLU (the second residual)         (1/8 grid, dense, width c8)
      -> 2x up, crop, depthwise 3x3x3 + 1x1 conv -> occupancy / offset   (1/4 grid, dense, width c4)
      -> 2x up, crop, two per-voxel MLPs -> occupancy / offset           (1/2 grid, sparse, width c2)
      -> per half-scale voxel: its 8 children's [logit, dx, dy, dz]     (full grid, sparse, width c1)

``(c8, _, c1) = head_channels`` and ``(c4, c2) = head_sparse_widths``. Below 1/4 every layer is
per voxel: the "2x up" maps one parent to its 8 children (a 1x1x1 conv + depth-to-space, as in
``head.py``), and the norms are over one voxel's channels (:class:`ChannelNorm`), never over the
volume. So any subset of voxels can be computed alone and gives exactly the values the dense volume
has there: :meth:`SparseReconHead.sparse` grows the occupied set coarse to fine (all 1/4 voxels,
which are few: lite 8,000 against 512,000 at full scale; the 1/2 children of the 1/4 voxels above
the gate; the full-scale children of the 1/2 voxels above it) with gathers and matmuls. A 1/2 voxel
is kept when its own occupancy and its parent's both pass the gate, so its ``gate_occupancy`` is
the smaller of the two and ``export.gate`` calibrates it unchanged.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from msdnet.training.config import ModelConfig
from msdnet.training.nn.blocks import group_norm
from msdnet.training.nn.encoder import level_shapes
from msdnet.training.nn.head import (
    CHILD_DX,
    CHILD_DY,
    CHILD_DZ,
    HeadOutputs,
    Up2x,
    conv3d_norm_relu,
    rows,
)


class ChannelNorm(nn.Module):
    """LayerNorm over the channel axis 1 of (B, C, ...) or (N, C): each voxel alone."""

    def __init__(self, channels: int, eps: float = 1e-5) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, x: Tensor) -> Tensor:
        mean = x.mean(dim=1, keepdim=True)
        var = (x - mean).pow(2).mean(dim=1, keepdim=True)
        shape = (1, -1) + (1,) * (x.dim() - 2)
        return (x - mean) / torch.sqrt(var + self.eps) * self.weight.reshape(shape) + self.bias.reshape(shape)


class VoxelMLP(nn.Module):
    """Norm -> ReLU -> 1x1x1 conv -> norm -> ReLU, width kept; on (B, c, D, H, W) or rows (N, c)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.norm_in = ChannelNorm(channels)
        self.lin = nn.Conv3d(channels, channels, 1)
        self.norm_out = ChannelNorm(channels)

    def forward(self, x: Tensor) -> Tensor:
        x = torch.relu(self.norm_in(x))
        x = self.lin(x) if x.dim() == 5 else rows(self.lin, x)
        return torch.relu(self.norm_out(x))


class DepthwiseBlock(nn.Module):
    """GroupNorm -> ReLU -> depthwise 3x3x3 conv -> 1x1x1 conv -> GroupNorm -> ReLU, width kept
    (the 1/4 level's spatial mixing at ~1/14 of a full 3x3x3 conv's cost)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            group_norm(channels),
            nn.ReLU(),
            nn.Conv3d(channels, channels, 3, padding=1, groups=channels),
            nn.Conv3d(channels, channels, 1, bias=False),
            group_norm(channels),
            nn.ReLU(),
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.body(x)


class SparseReconHead(HeadOutputs):
    """BEV features -> occupancy and offsets at scales 1/4, 1/2, 1; per voxel below 1/4."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c8, _, c1 = cfg.head_channels
        c4, c2 = cfg.head_sparse_widths
        self.d8 = level_shapes(cfg.grid)[-1][0]
        self.c8, self.c4, self.c2 = c8, c4, c2
        self.lift = nn.Conv2d(cfg.bev_channels, c8 * self.d8, 1)
        self.conv8 = conv3d_norm_relu(c8)
        self.conv8b = conv3d_norm_relu(c8)
        nn.init.zeros_(self.conv8b[1].weight)  # the residual block starts as the identity
        self.up4 = Up2x(c8, c4)
        self.post4 = DepthwiseBlock(c4)
        self.up2 = Up2x(c4, c2)
        self.post2 = nn.Sequential(VoxelMLP(c2), VoxelMLP(c2))
        self._add_outputs(cfg, c4, c2, c1)
        for name, v in (("child_dz", CHILD_DZ), ("child_dy", CHILD_DY), ("child_dx", CHILD_DX)):
            self.register_buffer(name, torch.tensor(v, dtype=torch.int64).reshape(1, 8), persistent=False)

    def _quarter(self, features: Tensor) -> Tensor:
        """F^D (B, C, H8, W8) -> the 1/4 volume (B, c4, D4, H4, W4) (dense: it is small)."""
        b, _, h8, w8 = features.shape
        x = self.lift(features).reshape(b, self.c8, self.d8, h8, w8)  # channel-major re-read
        x = self.conv8(torch.relu(x))  # (B, c8, D8, H8, W8)
        x = x + self.conv8b(x)
        return self.post4(self._crop(self.up4(x), 0))

    def _half(self, x4: Tensor) -> Tensor:
        """(B, c4, D4, H4, W4) -> (B, c2, D2, H2, W2), dense."""
        return self.post2(self._crop(self.up2(x4), 1))

    def multi_scale(self, features: Tensor, rows: Tensor | None = None) -> list[tuple[Tensor, Tensor]]:
        """F^D (B, C, H8, W8) -> per scale 1/4, 1/2, 1: (occupancy logits (B, 1, D_s, H_s, W_s),
        offsets (B, 3, D_s, H_s, W_s) metres [dx, dy, dz]), every voxel (training); ``rows`` as in
        ``ReconHead.multi_scale``."""
        x4 = self._quarter(features)
        x2 = self._half(x4)
        return [self._branches(x4, 0), self._branches(x2, 1), self._full_or_rows(x2, rows)]

    def packed(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """As ``ReconHead.packed``: (occupancy (B, 8, D2, H2, W2), offsets (B, 8, 3, D2, H2, W2))."""
        return self._packed_children(self._half(self._quarter(features)))

    def sparse(self, features: Tensor, gate: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Coarse-to-fine inference, batch 1, with ``ReconHead.sparse``'s outputs: occupancy (N, 8),
        offsets (N, 8, 3), voxels (N,) increasing half-scale index ``(z2 * H2 + y2) * W2 + x2``,
        gate_occupancy (N,) = min(own 1/2 occupancy, parent's 1/4 occupancy) > gate.
        With gate 0 every half-scale voxel is kept and the children equal :meth:`packed`'s."""
        (_, h4, w4), (d2, h2, w2) = self.shapes[0], self.shapes[1]
        x4 = self._quarter(features)  # (1, c4, D4, H4, W4)
        occ4 = torch.sigmoid(self.occ[0](x4)).reshape(-1)  # (D4 * H4 * W4,)
        keep4 = torch.nonzero(occ4 > gate).reshape(-1)  # (K,) the 1/4 voxels grown further
        f4 = x4.reshape(self.c4, -1).index_select(1, keep4).t()  # (K, c4)
        up = rows(self.up2.proj, f4).reshape(-1, 8, self.c2)  # (K, child, c2)
        z = torch.div(keep4, h4 * w4, rounding_mode="floor").unsqueeze(1) * 2 + self.child_dz  # (K, 8)
        y = torch.remainder(torch.div(keep4, w4, rounding_mode="floor"), h4).unsqueeze(1) * 2 + self.child_dy
        x = torch.remainder(keep4, w4).unsqueeze(1) * 2 + self.child_dx
        inside = ((z < d2) & (y < h2) & (x < w2)).reshape(-1)  # the crop to the 1/2 level's grid
        sel = torch.nonzero(inside).reshape(-1)  # (M,) children inside the grid
        vox = ((z * h2 + y) * w2 + x).reshape(-1).index_select(0, sel)  # (M,)
        parent = occ4.index_select(0, keep4).unsqueeze(1).expand(-1, 8).reshape(-1).index_select(0, sel)
        x2 = self.post2(up.reshape(-1, self.c2).index_select(0, sel))  # (M, c2)
        occ2 = torch.sigmoid(rows(self.occ[1], x2)).reshape(-1)  # (M,)
        gate_occ = torch.minimum(occ2, parent)
        keep2 = torch.nonzero(gate_occ > gate).reshape(-1)
        voxels, order = torch.sort(vox.index_select(0, keep2))  # increasing half-scale index
        keep2 = keep2.index_select(0, order)
        occ, off = self._row_children(x2.index_select(0, keep2))  # (N, 8), (N, 8, 3)
        return occ, off, voxels, gate_occ.index_select(0, keep2)

    def forward(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """Full scale only, dense layout: (occupancy (B, 1, D, H, W), offsets (B, 3, D, H, W))."""
        logits, off = self.multi_scale(features)[2]
        return torch.sigmoid(logits), off
