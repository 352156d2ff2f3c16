"""Small 2D building blocks shared by RGFD, the noise adapter, the light denoiser and the U-Net.

Every block maps BEV maps ``(B, C, H, W)`` and exports to ONNX opset 19 with the TorchScript
exporter (no ``LayerNorm`` over a permuted tensor, no adaptive pooling with odd sizes).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


def count_parameters(module: nn.Module) -> int:
    """Number of scalar parameters of ``module`` (trainable or not; buffers excluded)."""
    return sum(p.numel() for p in module.parameters())


def group_norm(channels: int, max_groups: int = 32, min_group_size: int = 4) -> nn.GroupNorm:
    """GroupNorm with the most groups (<= max_groups) that keep >= min_group_size channels each.

    Batch-independent (batch 1 and 1x1 maps train fine) and identical in train and eval mode.
    """
    groups = math.gcd(channels, max(1, min(max_groups, channels // min_group_size)))
    return nn.GroupNorm(groups, channels)


class ChannelAttention(nn.Module):
    """CBAM channel attention: sigmoid(MLP(avg-pool) + MLP(max-pool)) per channel.

    x: (B, C, H, W) -> (B, C, H, W) = x * a, a: (B, C, 1, 1).
    """

    def __init__(self, channels: int, reduction: int = 16) -> None:
        super().__init__()
        hidden = max(4, channels // reduction)
        self.mlp = nn.Sequential(
            nn.Conv2d(channels, hidden, 1), nn.ReLU(inplace=True), nn.Conv2d(hidden, channels, 1)
        )

    def forward(self, x: Tensor) -> Tensor:
        avg = x.mean(dim=(2, 3), keepdim=True)  # (B, C, 1, 1)
        mx = x.amax(dim=(2, 3), keepdim=True)  # (B, C, 1, 1)
        return x * torch.sigmoid(self.mlp(avg) + self.mlp(mx))


class SpatialAttention(nn.Module):
    """CBAM spatial attention: sigmoid(conv7x7([mean_C, max_C])) per cell.

    x: (B, C, H, W) -> (B, C, H, W) = x * a, a: (B, 1, H, W).
    """

    def __init__(self, kernel: int = 7) -> None:
        super().__init__()
        self.conv = nn.Conv2d(2, 1, kernel, padding=kernel // 2)

    def forward(self, x: Tensor) -> Tensor:
        pooled = torch.cat([x.mean(dim=1, keepdim=True), x.amax(dim=1, keepdim=True)], dim=1)
        return x * torch.sigmoid(self.conv(pooled))  # pooled: (B, 2, H, W) [mean, max]


class CBAM(nn.Module):
    """Convolutional Block Attention Module (Woo et al. 2018): channel then spatial attention.

    x: (B, C, H, W) -> (B, C, H, W).
    """

    def __init__(self, channels: int, reduction: int = 16, kernel: int = 7) -> None:
        super().__init__()
        self.channel = ChannelAttention(channels, reduction)
        self.spatial = SpatialAttention(kernel)

    def forward(self, x: Tensor) -> Tensor:
        return self.spatial(self.channel(x))


class ChannelLayerNorm(nn.Module):
    """LayerNorm over the channel axis of (B, C, H, W), written out so it exports without permutes.

    y = (x - mean_C(x)) / sqrt(var_C(x) + eps) * weight[c] + bias[c] (biased variance, as
    ``nn.LayerNorm``).
    """

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, x: Tensor) -> Tensor:
        mean = x.mean(dim=1, keepdim=True)  # (B, 1, H, W)
        centred = x - mean
        var = (centred * centred).mean(dim=1, keepdim=True)  # (B, 1, H, W)
        y = centred / torch.sqrt(var + self.eps)
        return y * self.weight[None, :, None, None] + self.bias[None, :, None, None]


class ConvNeXtBlock(nn.Module):
    """ConvNeXt block (Liu et al. 2022): dw 7x7 -> LayerNorm(C) -> 1x1 (4C) -> GELU -> 1x1 (C),
    scaled by a learnt per-channel layer scale, plus the input.

    x: (B, C, H, W) -> (B, C, H, W).
    """

    def __init__(self, channels: int, expansion: int = 4, layer_scale: float = 1e-6) -> None:
        super().__init__()
        self.dwconv = nn.Conv2d(channels, channels, 7, padding=3, groups=channels)
        self.norm = ChannelLayerNorm(channels)
        self.pw1 = nn.Conv2d(channels, expansion * channels, 1)  # 1x1 conv == per-cell Linear
        self.act = nn.GELU()
        self.pw2 = nn.Conv2d(expansion * channels, channels, 1)
        self.gamma = nn.Parameter(torch.full((channels,), layer_scale))

    def forward(self, x: Tensor) -> Tensor:
        y = self.pw2(self.act(self.pw1(self.norm(self.dwconv(x)))))
        return x + y * self.gamma[None, :, None, None]


class Bottleneck2d(nn.Module):
    """Residual bottleneck (MSDNet Sec. III-D): 1x1 compress -> 3x3 -> 1x1 restore, plus input.

    Each conv but the last is followed by GroupNorm + SiLU. x: (B, C, H, W) -> (B, C, H, W).
    """

    def __init__(self, channels: int, hidden: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(channels, hidden, 1),
            group_norm(hidden),
            nn.SiLU(),
            nn.Conv2d(hidden, hidden, 3, padding=1),
            group_norm(hidden),
            nn.SiLU(),
            nn.Conv2d(hidden, channels, 1),
        )

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)


def timestep_embedding(t: Tensor, dim: int, max_period: float = 10000.0) -> Tensor:
    """Sinusoidal embedding of diffusion step indices (DDPM / Transformer).

    t: (B,) float32 step index (0..T) -> (B, dim) float32 [cos(t f_0..f_{h-1}), sin(...)]
    with f_i = max_period^(-i/h), h = dim // 2; an odd dim gets a trailing zero column.
    """
    half = dim // 2
    freqs = torch.exp(
        -math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half
    )  # (half,)
    args = t.float()[:, None] * freqs[None, :]  # (B, half)
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=1)  # (B, 2 * half)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=1)
    return emb


class TimeEmbedding(nn.Module):
    """Sinusoidal step embedding followed by Linear -> SiLU -> Linear.

    t: (B,) float32 step index -> (B, out_dim).
    """

    def __init__(self, dim: int, out_dim: int | None = None) -> None:
        super().__init__()
        self.dim = dim
        out = out_dim or dim
        self.mlp = nn.Sequential(nn.Linear(dim, out), nn.SiLU(), nn.Linear(out, out))

    def forward(self, t: Tensor) -> Tensor:
        return self.mlp(timestep_embedding(t, self.dim))
