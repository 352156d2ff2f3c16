"""The U-Net of R2LDM as published (the authors' ``EfficientUNet``), written anew for our latents.

    x_t (B, 8, H, W) ++ cond (B, 8, H, W)   (the condition is concatenated at the input only)
      -> conv 3x3 (16 -> in_ch) -> conv 3x3 (in_ch -> C0)
      -> down blocks d1 (C0 -> C1, no resampling), d2 / d3 / d4 (conv to C_l, 2x down, blocks)
      -> up blocks u4 (C4 -> C3, 2x up), u3 (C3 + C3 -> C2, up), u2 (C2 + C2 -> C1, up),
         u1 (C1 + C1 -> C0), each after concatenating the matching down output
      -> conv 3x3 (C0 -> in_ch, zero-initialised) -> conv 3x3 (in_ch -> 8) = eps_hat

``C_l = base * multipliers[l - 1]``, ``C0 = base``; every block holds ``res_blocks`` residual
blocks: GroupNorm -> SiLU -> conv 3x3 -> adaptive GroupNorm (scale and shift from the time
embedding) -> SiLU -> conv 3x3 (zero-initialised), plus a 1x1 skip when the width changes, the sum
times 1/sqrt(2). The time embedding is sinusoidal of the log-SNR lambda (width ``base``) ->
Linear -> SiLU -> Linear (width 4 base). Convolutions pad circularly along W (``ring``, as the
published code, which comes from range-image LiDAR) and with zeros along H.

Differences from the published code (docs/training.md): resampling is 2x2 average pooling down and
nearest-neighbour 2x up (published: a [1, 3, 3, 1] FIR filter); spatial sizes that do not halve
evenly are cropped back to the skip's size on the way up.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from msdnet.training.published_config import PublishedR2LDMConfig

INV_SQRT2 = 1.0 / math.sqrt(2.0)


class RingConv2d(nn.Conv2d):
    """3x3 (or 1x1) conv, 'same' size: circular padding along W when ``ring``, zeros along H."""

    def __init__(self, cin: int, cout: int, kernel: int = 3, ring: bool = True) -> None:
        super().__init__(cin, cout, kernel, padding=0)
        self.p = kernel // 2
        self.ring = ring

    def forward(self, x: Tensor) -> Tensor:
        p = self.p
        if p:
            if self.ring:  # written with slices so that it exports as Slice + Concat
                x = torch.cat([x[..., -p:], x, x[..., :p]], dim=-1)
                x = F.pad(x, (0, 0, p, p))
            else:
                x = F.pad(x, (p, p, p, p))
        return super().forward(x)


def zero_init(module: nn.Module) -> nn.Module:
    """Set every parameter of ``module`` to zero (the residual starts as the identity)."""
    for param in module.parameters():
        nn.init.zeros_(param)
    return module


class AdaGroupNorm(nn.Module):
    """GroupNorm without affine, then ``h (1 + scale) + shift`` with (scale, shift) from the embedding."""

    def __init__(self, emb: int, channels: int, groups: int) -> None:
        super().__init__()
        self.norm = nn.GroupNorm(groups, channels, eps=1e-6, affine=False)
        self.proj = nn.Sequential(nn.SiLU(), nn.Linear(emb, 2 * channels))

    def forward(self, x: Tensor, temb: Tensor) -> Tensor:
        """x (B, C, H, W), temb (B, E) -> (B, C, H, W)."""
        scale, shift = self.proj(temb)[:, :, None, None].chunk(2, dim=1)
        return self.norm(x) * (1.0 + scale) + shift


class ResidualBlock(nn.Module):
    """The published residual block (module docstring)."""

    def __init__(self, cin: int, cout: int, emb: int, groups: int, ring: bool) -> None:
        super().__init__()
        self.norm1 = nn.GroupNorm(groups, cin, eps=1e-6)
        self.conv1 = RingConv2d(cin, cout, 3, ring)
        self.norm2 = AdaGroupNorm(emb, cout, groups)
        self.conv2 = zero_init(RingConv2d(cout, cout, 3, ring))
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: Tensor, temb: Tensor) -> Tensor:
        """x (B, cin, H, W), temb (B, E) -> (B, cout, H, W)."""
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h, temb)))
        return (self.skip(x) + h) * INV_SQRT2


class Level(nn.Module):
    """[conv to cout + 2x down] -> ``n`` residual blocks -> [2x up + conv]."""

    def __init__(self, cin: int, cout: int, n: int, emb: int, groups: int, ring: bool, mode: str) -> None:
        super().__init__()
        self.mode = mode  # "down": resample first; "up": resample last; "": none
        self.pre = RingConv2d(cin, cout, 3, ring) if mode == "down" else nn.Identity()
        first = cout if mode == "down" else cin
        self.blocks = nn.ModuleList(
            [ResidualBlock(first if i == 0 else cout, cout, emb, groups, ring) for i in range(n)]
        )
        self.post = RingConv2d(cout, cout, 3, ring) if mode == "up" else nn.Identity()

    def forward(self, h: Tensor, temb: Tensor) -> Tensor:
        """h (B, cin, H, W) -> (B, cout, H', W'), H' = ceil(H / 2), H or 2H."""
        if self.mode == "down":
            h = F.avg_pool2d(self.pre(h), 2, ceil_mode=True)
        for blk in self.blocks:
            h = blk(h, temb)
        if self.mode == "up":
            h = self.post(F.interpolate(h, scale_factor=2.0, mode="nearest"))
        return h


def logsnr_embedding(lam: Tensor, dim: int, max_period: float = 10000.0) -> Tensor:
    """lam (B,) log-SNR -> (B, dim) [sin(lam f_i), cos(lam f_i)], f_i = max_period^(-i / (dim/2 - 1))."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) / (half - 1) * torch.arange(half, device=lam.device))
    args = lam.float()[:, None] * freqs[None, :]
    return torch.cat([args.sin(), args.cos()], dim=1)


class PublishedUNet(nn.Module):
    """eps-prediction network: (x_t (B, L, H, W), lambda (B,) or (1,), cond (B, L, H, W)) -> (B, L, H, W)."""

    def __init__(self, cfg: PublishedR2LDMConfig) -> None:
        super().__init__()
        base, lat, ring, g = cfg.unet_base, cfg.latent_channels, cfg.ring, cfg.unet_groups
        emb = 4 * base
        self.base = base
        self.time = nn.Sequential(nn.Linear(base, emb), nn.SiLU(), nn.Linear(emb, emb))
        c = [base] + [base * m for m in cfg.unet_multipliers]  # C0 .. C4
        n = cfg.unet_res_blocks
        self.in_conv1 = RingConv2d(2 * lat, cfg.unet_in_channels, 3, ring)
        self.in_conv2 = RingConv2d(cfg.unet_in_channels, c[0], 3, ring)
        self.down = nn.ModuleList(
            [Level(c[0], c[1], n, emb, g, ring, "")]
            + [Level(c[i], c[i + 1], n, emb, g, ring, "down") for i in (1, 2, 3)]
        )
        self.up = nn.ModuleList(
            [
                Level(c[4], c[3], n, emb, g, ring, "up"),
                Level(2 * c[3], c[2], n, emb, g, ring, "up"),
                Level(2 * c[2], c[1], n, emb, g, ring, "up"),
                Level(2 * c[1], c[0], n, emb, g, ring, ""),
            ]
        )
        self.out_conv1 = zero_init(RingConv2d(c[0], cfg.unet_in_channels, 3, ring))
        self.out_conv2 = RingConv2d(cfg.unet_in_channels, lat, 3, ring)

    def forward(self, x_t: Tensor, lam: Tensor, cond: Tensor) -> Tensor:
        temb = self.time(logsnr_embedding(lam.reshape(-1).expand(x_t.shape[0]), self.base))  # (B, 4 base)
        h = self.in_conv2(self.in_conv1(torch.cat([x_t, cond], dim=1)))
        skips = []
        for level in self.down:
            h = level(h, temb)
            skips.append(h)
        h = self.up[0](h, temb)
        for level, skip in zip(self.up[1:], reversed(skips[:-1]), strict=True):
            h = level(torch.cat([h[..., : skip.shape[2], : skip.shape[3]], skip], dim=1), temb)
        return self.out_conv2(self.out_conv1(h))
