"""Reconstruction-Guided Feature Distillation network (MSDNet Sec. III-C, Fig. 2 bottom right).

F_r^S (B, C, H, W) -> F_r^R (B, C, H, W), C = cfg.bev_channels, R = cfg.rgfd_channels:

    F_r^S ─► Down(C→R, /2) ─► Down(R→2R, /4) ─► CBAM ─► ConvNeXt ─► CBAM ─► Up(2R→R, /2) ─► Up(R→R, /1) ─┐
      └──────────────────────────────── side path ─────────────────────────────────────► Aggregation ─► F_r^R

- Down block: 3x3 stride-2 standard conv, then a 3x3 deformable conv (each + GroupNorm + ReLU).
- Up block: 2x2 stride-2 transposed conv (+ GroupNorm + ReLU), cropped to the size of the matching
  encoder map, so odd sizes work (H -> ceil(H/2) -> ceil(H/4) -> back to H exactly).
- Aggregation: concatenate the two inputs and apply one 3x1 convolution (kernel 3 along H, 1 along
  W, as the paper states), giving F_r^R with no activation (the distillation target F_l^D is signed).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from msdnet.training.config import ModelConfig
from msdnet.training.nn.blocks import CBAM, ConvNeXtBlock, group_norm
from msdnet.training.nn.deform import DeformConv2d


class DownBlock(nn.Module):
    """Stride-2 3x3 conv + deformable 3x3 conv: (B, in, H, W) -> (B, out, ceil(H/2), ceil(W/2))."""

    def __init__(self, in_ch: int, out_ch: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_ch, out_ch, 3, stride=2, padding=1, bias=False)
        self.norm1 = group_norm(out_ch)
        self.deform = DeformConv2d(out_ch, out_ch, 3, stride=1, padding=1, bias=False)
        self.norm2 = group_norm(out_ch)
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        x = self.act(self.norm1(self.conv(x)))
        return self.act(self.norm2(self.deform(x)))


class UpBlock(nn.Module):
    """2x2 stride-2 transposed conv, cropped: (B, in, h, w) -> (B, out, H, W) with H <= 2h, W <= 2w."""

    def __init__(self, in_ch: int, out_ch: int) -> None:
        super().__init__()
        self.up = nn.ConvTranspose2d(in_ch, out_ch, 2, stride=2, bias=False)
        self.norm = group_norm(out_ch)
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: Tensor, size: tuple[int, int]) -> Tensor:
        y = self.up(x)[:, :, : size[0], : size[1]]  # (B, out, 2h, 2w) cropped to the skip size
        return self.act(self.norm(y))


class Aggregation(nn.Module):
    """Concatenate two maps and apply a 3x1 conv: (B, a, H, W), (B, b, H, W) -> (B, out, H, W)."""

    def __init__(self, in_a: int, in_b: int, out_ch: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_a + in_b, out_ch, (3, 1), padding=(1, 0))

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        return self.conv(torch.cat([a, b], dim=1))  # (B, a + b, H, W)


class RGFD(nn.Module):
    """RGFD feature reconstruction: F_r^S (B, C, H, W) -> F_r^R (B, C, H, W), C = cfg.bev_channels."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c, r = cfg.bev_channels, cfg.rgfd_channels
        self.down1 = DownBlock(c, r)
        self.down2 = DownBlock(r, 2 * r)
        self.attention = nn.Sequential(CBAM(2 * r), ConvNeXtBlock(2 * r), CBAM(2 * r))
        self.up1 = UpBlock(2 * r, r)
        self.up2 = UpBlock(r, r)
        self.aggregate = Aggregation(r, c, c)

    def forward(self, f_s: Tensor) -> Tensor:
        """f_s: (B, C, H, W) sparse radar BEV features -> (B, C, H, W) reconstructed features."""
        d1 = self.down1(f_s)  # (B, R, ceil(H/2), ceil(W/2))
        d2 = self.down2(d1)  # (B, 2R, ceil(H/4), ceil(W/4))
        a = self.attention(d2)
        u1 = self.up1(a, (d1.shape[2], d1.shape[3]))  # (B, R, ceil(H/2), ceil(W/2))
        u2 = self.up2(u1, (f_s.shape[2], f_s.shape[3]))  # (B, R, H, W)
        return self.aggregate(u2, f_s)
