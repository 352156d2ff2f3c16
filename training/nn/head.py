"""Progressive point-cloud reconstruction head (MSDNet Eq. 2-4; R2LDM's LPCR), shared by the
teacher and the student ("a common set of weights within the point cloud reconstruction network").

    F^D (B, C, H8, W8) -> 1x1 conv to c4 * D8 channels -> re-read as (B, c4, D8, H8, W8)
      -> 3x3x3 conv                                                      (1/8 grid)
      -> 2x up, crop, 3x3x3 conv -> occupancy / offset                   (1/4 grid, width c4)
      -> 2x up, crop, 3x3x3 conv -> occupancy / offset                   (1/2 grid, width c2)
      -> 2x up fused with the branches, crop -> occupancy / offset       (full grid, width c1)

``head_channels = (c4, c2, c1)``. Every "2x up" is a 2x2x2 stride-2 transposed convolution written
as a 1x1x1 convolution to ``8 * c_out`` channels followed by a depth-to-space shuffle (the same
function; fast in torch) and exported to ONNX as one ``ConvTranspose`` (:class:`Up2x`). The full
scale (paper: 40 x 320 x 320) is never materialised with c1 channels: per half-scale voxel a 1x1x1
conv gives its 8 children's c1 features, ReLU, then a grouped 1x1x1 conv gives each child's
[occupancy logit, dx, dy, dz]; only those 4 channels are shuffled to full resolution. Crops make
each scale exactly the encoder level's grid (lite D = 20 -> 3 at 1/8 -> 6 -> 5). At each scale:
occupancy = sigmoid(logit) (Eq. 3), offset = tanh(.) x half that scale's voxel size per axis
(Eq. 4), channels [dx, dy, dz] in metres.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import ClassVar

import torch
from torch import Tensor, nn

from msdnet.training.config import ModelConfig
from msdnet.training.data.targets import SCALE_FACTORS, scale_shapes
from msdnet.training.nn.blocks import group_norm
from msdnet.training.nn.encoder import level_shapes

# child (dz * 2 + dy) * 2 + dx of a voxel -> its (dz, dy, dx), the depth_to_space3d order
CHILD_DZ, CHILD_DY, CHILD_DX = ([c >> s & 1 for c in range(8)] for s in (2, 1, 0))


def conv3d_norm_relu(channels: int) -> nn.Sequential:
    """3x3x3 conv (padding 1) -> GroupNorm -> ReLU, width kept."""
    return nn.Sequential(
        nn.Conv3d(channels, channels, 3, padding=1, bias=False), group_norm(channels), nn.ReLU()
    )


def depth_to_space3d(x: Tensor, c_out: int) -> Tensor:
    """(B, 8 * c_out, D, H, W), channel = child * c_out + c with child = (dz * 2 + dy) * 2 + dx
    -> (B, c_out, 2D, 2H, 2W)."""
    b, _, d, h, w = x.shape
    x = x.reshape(b, 2, 2, 2, c_out, d, h, w)  # (B, dz, dy, dx, c, D, H, W)
    x = x.permute(0, 4, 5, 1, 6, 2, 7, 3)  # (B, c, D, dz, H, dy, W, dx)
    return x.reshape(b, c_out, 2 * d, 2 * h, 2 * w)


class Up2x(nn.Module):
    """2x2x2 stride-2 transposed conv as 1x1x1 conv + depth-to-space: (B, cin, D, H, W) ->
    (B, cout, 2D, 2H, 2W).

    In torch (training, eval, the torch peers) it runs as the 1x1x1 conv and the shuffle. In an
    ONNX export it is one ``ConvTranspose`` (kernel 2, stride 2) whose input carries an extra
    channel of ones, so the weight's last input row is the per-child bias (``ConvTranspose``'s own
    bias is per output channel only): the same products and sums, without the 8-D ``Transpose``
    that engines run slowly. ``export_style = "depth_to_space"`` exports the 1x1x1 conv and the
    shuffle as they are, the form of older model folders (``export.recover`` reads them with it)."""

    export_style: ClassVar[str] = "conv_transpose"  # or "depth_to_space": the older graph form

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.cout = cout
        self.proj = nn.Conv3d(cin, 8 * cout, 1)

    def forward(self, x: Tensor) -> Tensor:
        if torch.onnx.is_in_onnx_export() and Up2x.export_style == "conv_transpose":
            return self.as_conv_transpose(x)
        return depth_to_space3d(self.proj(x), self.cout)

    def as_conv_transpose(self, x: Tensor) -> Tensor:
        """The same map as one transposed convolution over ``[x, 1]``: (B, cin, D, H, W) ->
        (B, cout, 2D, 2H, 2W)."""
        cin, c = x.shape[1], self.cout
        w = self.proj.weight.reshape(2, 2, 2, c, cin).permute(4, 3, 0, 1, 2)  # (cin, cout, dz, dy, dx)
        b = self.proj.bias.reshape(2, 2, 2, c).permute(3, 0, 1, 2).unsqueeze(0)  # (1, cout, dz, dy, dx)
        ones = torch.ones_like(x[:, :1])  # (B, 1, D, H, W)
        return nn.functional.conv_transpose3d(torch.cat([x, ones], 1), torch.cat([w, b], 0), stride=2)


@contextmanager
def up_export_style(style: str) -> Iterator[None]:
    """Export every :class:`Up2x` in ``style`` (``conv_transpose`` or ``depth_to_space``) inside."""
    if style not in ("conv_transpose", "depth_to_space"):
        raise ValueError(f"style must be conv_transpose or depth_to_space, got {style!r}")
    before, Up2x.export_style = Up2x.export_style, style
    try:
        yield
    finally:
        Up2x.export_style = before


def rows(conv: nn.Conv3d, x: Tensor) -> Tensor:
    """A 1x1x1 conv on rows: x (N, cin) -> (N, cout) (ungrouped convs only)."""
    return x @ conv.weight.reshape(conv.out_channels, -1).t() + conv.bias


rows_of = rows  # for methods whose argument is named ``rows``


class HeadOutputs(nn.Module):
    """What every reconstruction head shares after its trunk: the occupancy / offset branches at
    1/4 and 1/2 (Eq. 3-4), the per-child full-scale layers ``up1`` / ``full`` and the crops, in
    the dense layout, the packed layout (``recon_head.onnx``) and on rows (``recon_head_sparse.onnx``)."""

    def _add_outputs(self, cfg: ModelConfig, c4: int, c2: int, c1: int) -> None:
        """Create the output layers (after the trunk's, so seeded initialisation keeps its order)."""
        self.shapes = scale_shapes(cfg.grid)  # (D, H, W) per scale 1/4, 1/2, 1
        self.up1 = nn.Conv3d(c2, 8 * c1, 1)  # per half-scale voxel: its 8 children's c1 features
        self.full = nn.Conv3d(8 * c1, 8 * 4, 1, groups=8)  # per child: [logit, dx, dy, dz]
        self.occ = nn.ModuleList([nn.Conv3d(c, 1, 1) for c in (c4, c2)])
        self.off = nn.ModuleList([nn.Conv3d(c, 3, 1) for c in (c4, c2)])
        prior = math.log(cfg.occupancy_prior / (1.0 - cfg.occupancy_prior))
        for conv in self.occ:
            nn.init.constant_(conv.bias, prior)  # start at the typical occupancy, not at 0.5
        with torch.no_grad():
            self.full.bias.reshape(8, 4)[:, 0] = prior
        half = torch.tensor(cfg.grid.voxel_size, dtype=torch.float32) / 2.0  # [vx, vy, vz] / 2
        for s, k in enumerate(SCALE_FACTORS):
            self.register_buffer(f"half_size_{s}", (half * k).reshape(1, 3, 1, 1, 1), persistent=False)

    def _crop(self, x: Tensor, s: int) -> Tensor:
        d, h, w = self.shapes[s]
        return x[:, :, :d, :h, :w]

    def _branches(self, x: Tensor, s: int) -> tuple[Tensor, Tensor]:
        """x (B, c, D, H, W) at scale s (1/4 or 1/2) -> (occupancy logits (B, 1, D, H, W),
        offsets (B, 3, D, H, W))."""
        half = getattr(self, f"half_size_{s}")
        return self.occ[s](x), torch.tanh(self.off[s](x)) * half

    def _full(self, x2: Tensor) -> tuple[Tensor, Tensor]:
        """x2 (B, c2, D2, H2, W2) -> full scale (logits (B, 1, D, H, W), offsets (B, 3, D, H, W))."""
        y = self._crop(depth_to_space3d(self.full(torch.relu(self.up1(x2))), 4), 2)  # (B, 4, D, H, W)
        return y[:, :1], torch.tanh(y[:, 1:]) * self.half_size_2

    def _full_or_rows(self, x2: Tensor, rows: Tensor | None) -> tuple[Tensor, Tensor]:
        """The full scale of ``multi_scale``: dense (:meth:`_full`) when ``rows`` is None, else
        only the children of the half-scale voxels ``rows`` (N,) int64, linear in the flattened
        (B, D2, H2, W2): (logits (N, 8), offsets (N, 8, 3) metres [dx, dy, dz]), axis 1 the
        child ``(dz * 2 + dy) * 2 + dx`` (training/models/full_rows.py)."""
        if rows is None:
            return self._full(x2)
        feats = x2.permute(0, 2, 3, 4, 1).reshape(-1, x2.shape[1]).index_select(0, rows)  # (N, c2)
        h = torch.relu(rows_of(self.up1, feats))  # (N, 8 * c1)
        y = (h @ self._full_block().t() + self.full.bias).reshape(-1, 8, 4)  # (N, child, 4)
        return y[:, :, 0], torch.tanh(y[:, :, 1:]) * self.half_size_2.reshape(1, 1, 3)

    def _packed_children(self, x2: Tensor) -> tuple[Tensor, Tensor]:
        """x2 (B, c2, D2, H2, W2) -> (occupancy (B, 8, D2, H2, W2), offsets (B, 8, 3, D2, H2, W2)),
        axis 1 the child ``(dz * 2 + dy) * 2 + dx`` (the ``packed`` layout)."""
        y = self.full(torch.relu(self.up1(x2)))  # (B, 8 * 4, D2, H2, W2)
        b, _, d2, h2, w2 = y.shape
        y = y.reshape(b, 8, 4, d2, h2, w2)  # (B, child, [logit, dx, dy, dz], D2, H2, W2)
        half = self.half_size_2.reshape(1, 1, 3, 1, 1, 1)
        return torch.sigmoid(y[:, :, 0]), torch.tanh(y[:, :, 1:]) * half

    def _row_children(self, feats: Tensor) -> tuple[Tensor, Tensor]:
        """feats (N, c2) of N half-scale voxels -> (occupancy (N, 8), offsets (N, 8, 3)): one
        matmul to the 8 children's c1 features, ReLU, one block-diagonal matmul to each child's
        [logit, dx, dy, dz] (the weights of ``up1`` / ``full``)."""
        h = torch.relu(rows(self.up1, feats))  # (N, 8 * c1)
        y = (h @ self._full_block().t() + self.full.bias).reshape(-1, 8, 4)  # (N, child, 4)
        half = self.half_size_2.reshape(1, 1, 3)
        return torch.sigmoid(y[:, :, 0]), torch.tanh(y[:, :, 1:]) * half

    def _full_block(self) -> Tensor:
        """The grouped 1x1x1 ``full`` conv as one block-diagonal (8 * 4, 8 * c1) matrix."""
        w = self.full.weight.reshape(8, 4, 1, -1)  # (group = child, out, 1, c1)
        eye = torch.eye(8, dtype=w.dtype, device=w.device).reshape(8, 1, 8, 1)
        return (w * eye).reshape(32, -1)  # row child * 4 + out, column child' * c1 + c


class ReconHead(HeadOutputs):
    """BEV features -> occupancy and offsets at scales 1/4, 1/2, 1."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c4, c2, c1 = cfg.head_channels
        self.d8 = level_shapes(cfg.grid)[-1][0]
        self.c4 = c4
        self.lift = nn.Conv2d(cfg.bev_channels, c4 * self.d8, 1)
        self.conv8 = conv3d_norm_relu(c4)
        self.up4 = Up2x(c4, c4)
        self.post4 = nn.Sequential(group_norm(c4), nn.ReLU(), conv3d_norm_relu(c4))
        self.up2 = Up2x(c4, c2)
        self.post2 = nn.Sequential(group_norm(c2), nn.ReLU(), conv3d_norm_relu(c2))
        self._add_outputs(cfg, c4, c2, c1)

    def _eighth(self, features: Tensor) -> Tensor:
        """F^D (B, C, H8, W8) -> the 1/8 volume (B, c4, D8, H8, W8)."""
        b, _, h8, w8 = features.shape
        x = self.lift(features).reshape(b, self.c4, self.d8, h8, w8)  # channel-major re-read
        return self.conv8(torch.relu(x))

    def _quarter(self, features: Tensor) -> Tensor:
        """F^D (B, C, H8, W8) -> the 1/4 volume (B, c4, D4, H4, W4)."""
        return self.post4(self._crop(self.up4(self._eighth(features)), 0))

    def _trunk(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """F^D (B, C, H8, W8) -> volumes at 1/4 (c4) and 1/2 (c2)."""
        x4 = self._quarter(features)  # (B, c4, D4, H4, W4)
        x2 = self.post2(self._crop(self.up2(x4), 1))  # (B, c2, D2, H2, W2)
        return x4, x2

    def multi_scale(self, features: Tensor, rows: Tensor | None = None) -> list[tuple[Tensor, Tensor]]:
        """F^D (B, C, H8, W8) -> per scale 1/4, 1/2, 1: (occupancy logits (B, 1, D_s, H_s, W_s),
        offsets (B, 3, D_s, H_s, W_s) metres [dx, dy, dz]). Logits, for a stable BCE (Eq. 5).
        ``rows``: the full scale only under these half-scale voxels (:meth:`_full_or_rows`)."""
        x4, x2 = self._trunk(features)
        return [self._branches(x4, 0), self._branches(x2, 1), self._full_or_rows(x2, rows)]

    def packed(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """Inference at full scale without the depth-to-space (``recon_head.onnx``): F^D (B, C, H8, W8)
        -> (occupancy (B, 8, D2, H2, W2) in [0, 1], offsets (B, 8, 3, D2, H2, W2) metres [dx, dy, dz]),
        axis 1 the child ``(dz * 2 + dy) * 2 + dx`` of half-scale voxel [z2, y2, x2], i.e. full-scale
        voxel [2 z2 + dz, 2 y2 + dy, 2 x2 + dx]. The runtime decoder reads this layout directly,
        saving a full-resolution transpose (400 ms on the paper grid)."""
        return self._packed_children(self._trunk(features)[1])

    def sparse(self, features: Tensor, gate: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Coarse-to-fine inference (``recon_head_sparse.onnx``), batch 1: the trunk to the half
        scale as in :meth:`packed`, then the full scale only under the half-scale voxels whose
        own occupancy (the 1/2-scale branch, Eq. 3) exceeds ``gate``, computed sparsely: gather
        their c2 features, one matmul to their 8 children's c1 features, ReLU, one block-diagonal
        matmul to each child's [logit, dx, dy, dz] (the same weights as ``up1`` / ``full``).

        features: F^D (1, C, H8, W8); gate: (1,) float32 in [0, 1). -> occupancy (N, 8) in
        [0, 1], offsets (N, 8, 3) metres [dx, dy, dz] (axis 1 the child ``(dz * 2 + dy) * 2 + dx``
        as in :meth:`packed`), voxels (N,) int64 linear half-scale index ``(z2 * H2 + y2) * W2 + x2``
        in increasing order, gate_occupancy (N,) the half-scale occupancy of each kept voxel.
        With gate 0 every voxel is kept and the children equal :meth:`packed`'s."""
        x2 = self._trunk(features)[1]  # (1, c2, D2, H2, W2)
        c2 = x2.shape[1]
        half_occ = torch.sigmoid(self.occ[1](x2)).reshape(-1)  # (D2 * H2 * W2,)
        voxels = torch.nonzero(half_occ > gate).reshape(-1)  # (N,) the rulebook of kept voxels
        occ, off = self._row_children(x2.reshape(c2, -1).index_select(1, voxels).t())  # from (N, c2)
        return occ, off, voxels, half_occ[voxels]

    def forward(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """Inference, full scale only, in the dense layout: F^D (B, C, H8, W8) ->
        (occupancy (B, 1, D, H, W) in [0, 1], offsets (B, 3, D, H, W) metres [dx, dy, dz])."""
        logits, off = self._full(self._trunk(features)[1])
        return torch.sigmoid(logits), off
