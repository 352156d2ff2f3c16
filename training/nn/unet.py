"""R2LDM's latent diffusion U-Net (R2LDM Sec. III-C) and its exportable DDIM step.

A DDPM-style U-Net over unit-variance BEV latents (training/models/latent.py). Inputs: x_t (B, C, H, W),
the step t and the radar condition c = F_r^S (B, C, H, W); output eps_hat (B, C, H, W).

Conditioning (concatenation, R2LDM Tab. V b), at every level: c is normalised per sample
(GroupNorm: the raw F_r^S is far smaller than x_t, and unnormalised the U-Net learns to ignore
it; docs/training.md), concatenated to x_t
at the input, and projected to ``cfg.r2ldm_cond_channels`` channels that are average-pooled to each
level's resolution and concatenated to the input of every residual block.

Widths: ``cfg.r2ldm_channels`` per level, the first at least 2C, so the input convolution (2C in)
and the output convolution (C out) do not squeeze the noise through a narrower map (a narrower
U-Net does worse than the linear guess below). Each level has
``num_res_blocks`` residual blocks with the time embedding added per channel and a stride-2 3x3
conv between levels; the middle has a residual block and self-attention at the lowest resolution;
the decoder has ``num_res_blocks + 1`` blocks per level fed by skips (DDPM). Upsampling is
nearest x2 cropped to the skip's size, so odd sizes work (lite: 20 -> 10 -> 20).

Output: ``eps_hat = sqrt(1 - abar_t) x_t + out(...)``, the output convolution zero-initialised (as
:class:`~msdnet.training.nn.denoiser.LightDenoiser`): on unit-variance latents
``sqrt(1 - abar_t) x_t`` is the best linear guess of eps (its MSE is abar_t), so
training starts there and the network learns what the latent structure and the radar add.

The step (:class:`R2LDMStep`) clips the x0 estimate to ``+-cfg.r2ldm_x0_clip``: R2LDM samples from
pure noise, and near t = T the estimate divides by the tiny sqrt(abar_T), so an unclipped sampler
drifts far from the unit-variance latents.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from msdnet.runtime.spec.ddim import alphas_cumprod
from msdnet.training.config import ModelConfig
from msdnet.training.nn.blocks import TimeEmbedding, group_norm


class ResBlock(nn.Module):
    """GN-SiLU-conv3x3, + time embedding per channel, GN-SiLU-conv3x3, plus (1x1-projected) input.

    x: (B, in, H, W), temb: (B | 1, T) -> (B, out, H, W).
    """

    def __init__(self, in_ch: int, out_ch: int, temb_dim: int) -> None:
        super().__init__()
        self.block1 = nn.Sequential(group_norm(in_ch), nn.SiLU(), nn.Conv2d(in_ch, out_ch, 3, padding=1))
        self.temb = nn.Sequential(nn.SiLU(), nn.Linear(temb_dim, out_ch))
        self.block2 = nn.Sequential(group_norm(out_ch), nn.SiLU(), nn.Conv2d(out_ch, out_ch, 3, padding=1))
        self.skip = nn.Conv2d(in_ch, out_ch, 1) if in_ch != out_ch else nn.Identity()

    def forward(self, x: Tensor, temb: Tensor) -> Tensor:
        h = self.block1(x) + self.temb(temb)[:, :, None, None]
        return self.skip(x) + self.block2(h)


class SelfAttention2d(nn.Module):
    """Multi-head self-attention over the H*W cells, residual: (B, C, H, W) -> (B, C, H, W)."""

    def __init__(self, channels: int, head_dim: int = 64) -> None:
        super().__init__()
        # the most heads of >= head_dim channels that divide the width (480 -> 6 heads of 80)
        self.heads = max(h for h in range(1, max(1, channels // head_dim) + 1) if channels % h == 0)
        self.norm = group_norm(channels)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.out = nn.Conv2d(channels, channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        b, c, h, w = x.shape
        d = c // self.heads
        qkv = self.qkv(self.norm(x)).reshape(b, 3, self.heads, d, h * w)  # (B, [q,k,v], heads, d, N)
        q, k, v = qkv[:, 0], qkv[:, 1], qkv[:, 2]  # each (B, heads, d, N)
        attn = torch.softmax(torch.matmul(q.transpose(2, 3), k) * d**-0.5, dim=-1)  # (B, heads, N, N)
        y = torch.matmul(v, attn.transpose(2, 3))  # (B, heads, d, N)
        return x + self.out(y.reshape(b, c, h, w))


def _pool_to(c: Tensor, size: torch.Size) -> Tensor:
    """Average-pool a condition map (B, K, H, W) by 2 (ceil) until it is ``size`` (h, w)."""
    while c.shape[2:] != size:
        c = F.avg_pool2d(c, 2, ceil_mode=True)
    return c


class R2LDMUNet(nn.Module):
    """eps-prediction U-Net: (x_t (B, C, H, W), t (B,) or (1,) float32, cond (B, C, H, W)) -> (B, C, H, W).

    C = cfg.bev_channels; widths = cfg.r2ldm_channels (one level each, the first >= 2C);
    K = cfg.r2ldm_cond_channels condition channels concatenated into every residual block.
    """

    def __init__(self, cfg: ModelConfig, num_res_blocks: int = 1) -> None:
        super().__init__()
        c, widths, k = cfg.bev_channels, tuple(cfg.r2ldm_channels), cfg.r2ldm_cond_channels
        if widths[0] < 2 * c:
            raise ValueError(f"r2ldm_channels[0] must be >= 2 * bev_channels ({2 * c}), got {widths[0]}")
        temb = widths[0]  # time-embedding width (DDPM: 4 w0; w0 keeps R2LDM near 2x MSDNet)
        self.time_embed = TimeEmbedding(widths[0], temb)
        self.cond_norm = group_norm(c)  # per-sample unit variance of F_r^S
        self.cond_proj = nn.Sequential(nn.Conv2d(c, k, 3, padding=1), nn.SiLU())  # (B, K, H, W)
        self.conv_in = nn.Conv2d(2 * c, widths[0], 3, padding=1)
        self.down_blocks = nn.ModuleList()
        self.downsample = nn.ModuleList()
        skips = [widths[0]]  # channel count of every map pushed onto the skip stack
        ch = widths[0]
        for i, w in enumerate(widths):
            for _ in range(num_res_blocks):
                self.down_blocks.append(ResBlock(ch + k, w, temb))
                ch = w
                skips.append(ch)
            if i < len(widths) - 1:
                self.downsample.append(nn.Conv2d(ch, ch, 3, stride=2, padding=1))
                skips.append(ch)
        self.mid_block = ResBlock(ch + k, ch, temb)
        self.mid_attn = SelfAttention2d(ch)
        self.up_blocks = nn.ModuleList()
        self.upsample = nn.ModuleList()
        for i, w in reversed(list(enumerate(widths))):
            for _ in range(num_res_blocks + 1):
                self.up_blocks.append(ResBlock(ch + skips.pop() + k, w, temb))
                ch = w
            if i > 0:
                self.upsample.append(nn.Conv2d(ch, ch, 3, padding=1))
        self.num_res_blocks = num_res_blocks
        self.levels = len(widths)
        self.out = nn.Sequential(group_norm(ch), nn.SiLU(), nn.Conv2d(ch, c, 3, padding=1))
        nn.init.zeros_(self.out[2].weight)
        nn.init.zeros_(self.out[2].bias)
        noise_scale = np.sqrt(1.0 - alphas_cumprod(cfg.diffusion)).astype(np.float32)  # (T + 1,)
        self.register_buffer("noise_scale", torch.tensor(noise_scale), persistent=False)

    def forward(self, x_t: Tensor, t: Tensor, cond: Tensor) -> Tensor:
        temb = self.time_embed(t)  # (B | 1, w0)
        c = self.cond_norm(cond)  # (B, C, H, W), unit variance per sample and group
        ck = self.cond_proj(c)  # (B, K, H, W), concatenated into every block at its level

        def block(blk: ResBlock, h: Tensor) -> Tensor:
            return blk(torch.cat([h, _pool_to(ck, h.shape[2:])], dim=1), temb)

        h = self.conv_in(torch.cat([x_t, c], dim=1))  # (B, w0, H, W)
        stack = [h]
        blocks = iter(self.down_blocks)
        for i in range(self.levels):
            for _ in range(self.num_res_blocks):
                h = block(next(blocks), h)
                stack.append(h)
            if i < self.levels - 1:
                h = self.downsample[i](h)  # (B, w, ceil(h/2), ceil(w/2))
                stack.append(h)
        h = self.mid_attn(block(self.mid_block, h))
        blocks = iter(self.up_blocks)
        for i in range(self.levels):
            for _ in range(self.num_res_blocks + 1):
                h = block(next(blocks), torch.cat([h, stack.pop()], dim=1))
            if i < self.levels - 1:
                size = stack[-1].shape[2:]  # the next skip's (H, W): crop the x2 map to it
                h = F.interpolate(h, scale_factor=2.0, mode="nearest")[:, :, : size[0], : size[1]]
                h = self.upsample[i](h)
        skip = self.noise_scale[t.long()].reshape(-1, 1, 1, 1) * x_t  # sqrt(1 - abar_t) x_t
        return skip + self.out(h)


def ddim_update_clipped(x_t: Tensor, eps: Tensor, abar_t: Tensor, abar_prev: Tensor, clip: float) -> Tensor:
    """DDIM (eta = 0) with the x0 estimate clipped to [-clip, clip] (clip <= 0: no clip).

    x0 = clamp((x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t)); eps' = (x_t - sqrt(abar_t) x0) /
    sqrt(1 - abar_t) (the noise that x0 implies); x_prev = sqrt(abar_prev) x0 + sqrt(1 - abar_prev) eps'.
    Unclipped, this is ``denoiser.ddim_update`` exactly.
    """
    a_t = abar_t.reshape(-1, 1, 1, 1)  # (1 | B, 1, 1, 1) broadcast over (B, C, H, W)
    a_prev = abar_prev.reshape(-1, 1, 1, 1)
    x0 = (x_t - torch.sqrt(1.0 - a_t) * eps) / torch.sqrt(a_t)
    if clip > 0:
        x0 = x0.clamp(-clip, clip)
        eps = (x_t - torch.sqrt(a_t) * x0) / torch.sqrt(1.0 - a_t)
    return torch.sqrt(a_prev) * x0 + torch.sqrt(1.0 - a_prev) * eps


class R2LDMStep(nn.Module):
    """One DDIM step of R2LDM with the x0 clip of ``cfg.r2ldm_x0_clip`` and classifier-free
    guidance ``eps = eps(x, 0) + w (eps(x, c) - eps(x, 0))``, w = ``guidance`` (1: one U-Net call;
    otherwise both in one batch of 2B).

    forward(x_t (B, C, H, W), cond (B, C, H, W), t (1,), abar_t (1,), abar_prev (1,)) -> x_prev
    (the input order of ``runtime.model.onnx_spec.R2LDM_STEP``).
    """

    def __init__(self, unet: R2LDMUNet, x0_clip: float = 0.0, guidance: float = 1.0) -> None:
        super().__init__()
        self.unet = unet
        self.x0_clip = float(x0_clip)
        self.guidance = float(guidance)

    def forward(self, x_t: Tensor, cond: Tensor, t: Tensor, abar_t: Tensor, abar_prev: Tensor) -> Tensor:
        if self.guidance == 1.0:
            eps = self.unet(x_t, t, cond)
        else:
            both = self.unet(torch.cat([x_t, x_t]), t, torch.cat([cond, torch.zeros_like(cond)]))
            eps_c, eps_0 = both.chunk(2)  # each (B, C, H, W)
            eps = eps_0 + self.guidance * (eps_c - eps_0)
        return ddim_update_clipped(x_t, eps, abar_t, abar_prev, self.x0_clip)
