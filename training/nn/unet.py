"""R2LDM's latent diffusion U-Net (R2LDM Sec. III-C) and its exportable DDIM step.

A DDPM-style U-Net over BEV latents: input ``cat(x_t, cond)`` (B, 2C, H, W), where ``cond`` is the
radar latent (concatenation conditioning, R2LDM Tab. V b), output eps_hat (B, C, H, W). Levels use
``cfg.r2ldm_channels`` widths; each level has ``num_res_blocks`` residual blocks with the time
embedding added per channel, a stride-2 3x3 conv between levels, one residual block and
self-attention in the middle at the lowest resolution, and skip connections from every encoder
block into the decoder (DDPM: ``num_res_blocks + 1`` decoder blocks per level). Upsampling is
nearest x2 cropped to the skip's size, so odd sizes work (lite: 20 -> 10 -> 5 -> 10 -> 20).

Size: with one block per level and one middle block the paper preset (128, 256, 512) has 35.9 M
parameters, so R2LDM with its two encoders and the head lands near the paper's 40.3 M (DDPM's two
blocks per level and two middle blocks would give 58 M).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from msdnet.training.config import ModelConfig
from msdnet.training.nn.blocks import TimeEmbedding, group_norm
from msdnet.training.nn.denoiser import ddim_update


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
        self.heads = max(1, channels // head_dim)
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


class R2LDMUNet(nn.Module):
    """eps-prediction U-Net: (x_t (B, C, H, W), t (B,) or (1,) float32, cond (B, C, H, W)) -> (B, C, H, W).

    C = cfg.bev_channels; widths = cfg.r2ldm_channels (one level each).
    """

    def __init__(self, cfg: ModelConfig, num_res_blocks: int = 1) -> None:
        super().__init__()
        c, widths = cfg.bev_channels, tuple(cfg.r2ldm_channels)
        temb = 4 * widths[0]
        self.time_embed = TimeEmbedding(widths[0], temb)
        self.conv_in = nn.Conv2d(2 * c, widths[0], 3, padding=1)
        self.down_blocks = nn.ModuleList()
        self.downsample = nn.ModuleList()
        skips = [widths[0]]  # channel count of every map pushed onto the skip stack
        ch = widths[0]
        for i, w in enumerate(widths):
            for _ in range(num_res_blocks):
                self.down_blocks.append(ResBlock(ch, w, temb))
                ch = w
                skips.append(ch)
            if i < len(widths) - 1:
                self.downsample.append(nn.Conv2d(ch, ch, 3, stride=2, padding=1))
                skips.append(ch)
        self.mid_block = ResBlock(ch, ch, temb)
        self.mid_attn = SelfAttention2d(ch)
        self.up_blocks = nn.ModuleList()
        self.upsample = nn.ModuleList()
        for i, w in reversed(list(enumerate(widths))):
            for _ in range(num_res_blocks + 1):
                self.up_blocks.append(ResBlock(ch + skips.pop(), w, temb))
                ch = w
            if i > 0:
                self.upsample.append(nn.Conv2d(ch, ch, 3, padding=1))
        self.num_res_blocks = num_res_blocks
        self.levels = len(widths)
        self.out = nn.Sequential(group_norm(ch), nn.SiLU(), nn.Conv2d(ch, c, 3, padding=1))

    def forward(self, x_t: Tensor, t: Tensor, cond: Tensor) -> Tensor:
        temb = self.time_embed(t)  # (B | 1, 4 w0)
        h = self.conv_in(torch.cat([x_t, cond], dim=1))  # (B, w0, H, W)
        stack = [h]
        blocks = iter(self.down_blocks)
        for i in range(self.levels):
            for _ in range(self.num_res_blocks):
                h = next(blocks)(h, temb)
                stack.append(h)
            if i < self.levels - 1:
                h = self.downsample[i](h)  # (B, w, ceil(h/2), ceil(w/2))
                stack.append(h)
        h = self.mid_attn(self.mid_block(h, temb))
        blocks = iter(self.up_blocks)
        for i in range(self.levels):
            for _ in range(self.num_res_blocks + 1):
                h = next(blocks)(torch.cat([h, stack.pop()], dim=1), temb)
            if i < self.levels - 1:
                size = stack[-1].shape[2:]  # the next skip's (H, W): crop the x2 map to it
                h = F.interpolate(h, scale_factor=2.0, mode="nearest")[:, :, : size[0], : size[1]]
                h = self.upsample[i](h)
        return self.out(h)


class R2LDMStep(nn.Module):
    """One DDIM step of R2LDM, the update shared with :class:`DenoiserStep` (``ddim_update``).

    forward(x_t (B, C, H, W), cond (B, C, H, W), t (1,), abar_t (1,), abar_prev (1,)) -> x_prev
    (the input order of ``runtime.onnx_spec.R2LDM_STEP``).
    """

    def __init__(self, unet: R2LDMUNet) -> None:
        super().__init__()
        self.unet = unet

    def forward(self, x_t: Tensor, cond: Tensor, t: Tensor, abar_t: Tensor, abar_prev: Tensor) -> Tensor:
        return ddim_update(x_t, self.unet(x_t, t, cond), abar_t, abar_prev)
