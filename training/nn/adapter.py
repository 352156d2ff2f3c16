"""Noise adapter (MSDNet Sec. III-D, Eq. 11-12, Fig. 3): puts F_r^R at the predefined step m.

    g     = Linear(GAP(Bottleneck(F_r^R)))               global feature, (B, A)
    e     = TimeEmbedding(m)                             embedding of the start step, (1, A)
    logit = MLP(g + e) reshaped to (B, 2, C)             two logits per channel
    delta = softmax(logit, dim=1)[:, 0]                  gate, (B, C) -> (B, C, 1, 1)
    x_m   = delta * F_r^R + (1 - delta) * eps            Eq. 12, eps ~ N(0, I) passed in

Softmax shape (the paper leaves it open): one two-way softmax per sample and per channel, so each
channel can take its own mix of features and noise; delta is strictly inside (0, 1).
The last layer's bias starts the gate at delta_0 = sqrt(abar_m) / (sqrt(abar_m) + sqrt(1 - abar_m)),
the feature-to-noise ratio of the forward chain at step m (Eq. 9), so x_m starts with the signal-to-
noise ratio the denoiser was trained on; the weights learn the per-sample correction.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from msdnet.runtime.spec.ddim import alphas_cumprod
from msdnet.training.config import ModelConfig
from msdnet.training.nn.blocks import Bottleneck2d, TimeEmbedding


def initial_gate(cfg: ModelConfig) -> float:
    """delta_0 = sqrt(abar_m) / (sqrt(abar_m) + sqrt(1 - abar_m)) for m = cfg.diffusion.start_step."""
    abar = float(alphas_cumprod(cfg.diffusion)[cfg.diffusion.start_step])
    return math.sqrt(abar) / (math.sqrt(abar) + math.sqrt(1.0 - abar))


class NoiseAdapter(nn.Module):
    """(F_r^R (B, C, H, W), eps (B, C, H, W)) -> x_m (B, C, H, W); C = cfg.bev_channels."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c, a = cfg.bev_channels, cfg.adapter_hidden
        self.channels = c
        self.bottleneck = Bottleneck2d(c, a)
        self.global_proj = nn.Linear(c, a)
        self.time_embed = TimeEmbedding(cfg.time_embed_dim, a)
        self.mlp = nn.Sequential(nn.Linear(a, a), nn.SiLU(), nn.Linear(a, 2 * c))
        d0 = initial_gate(cfg)
        with torch.no_grad():
            bias = self.mlp[2].bias.view(2, c)  # [feature logits, noise logits]
            bias[0].fill_(math.log(d0))
            bias[1].fill_(math.log(1.0 - d0))
        self.register_buffer(
            "start_step", torch.tensor([float(cfg.diffusion.start_step)]), persistent=False
        )  # (1,) float32: m

    def gate(self, f_r: Tensor) -> Tensor:
        """f_r: (B, C, H, W) -> delta (B, C, 1, 1) in (0, 1)."""
        g = self.global_proj(self.bottleneck(f_r).mean(dim=(2, 3)))  # (B, A)
        e = self.time_embed(self.start_step)  # (1, A)
        logits = self.mlp(g + e).reshape(-1, 2, self.channels)  # (B, 2, C) [feature, noise]
        delta = torch.softmax(logits, dim=1)[:, 0]  # (B, C)
        return delta[:, :, None, None]

    @staticmethod
    def mix(f_r: Tensor, eps: Tensor, delta: Tensor) -> Tensor:
        """Eq. 12: f_r, eps (B, C, H, W), delta (B, C, 1, 1) -> delta * f_r + (1 - delta) * eps."""
        return delta * f_r + (1.0 - delta) * eps

    def forward(self, f_r: Tensor, eps: Tensor) -> Tensor:
        """f_r, eps: (B, C, H, W) -> x_m = delta * f_r + (1 - delta) * eps, (B, C, H, W)."""
        return self.mix(f_r, eps, self.gate(f_r))


class ForwardNoising(nn.Module):
    """The ablation without a noise adapter: x_m is the forward chain at m (Eq. 9),
    ``sqrt(abar_m) * F_r^R + sqrt(1 - abar_m) * eps``, the same for every input."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        abar = float(alphas_cumprod(cfg.diffusion)[cfg.diffusion.start_step])
        self.signal, self.noise = math.sqrt(abar), math.sqrt(1.0 - abar)

    def forward(self, f_r: Tensor, eps: Tensor) -> Tensor:
        """f_r, eps: (B, C, H, W) -> x_m (B, C, H, W)."""
        return self.signal * f_r + self.noise * eps
