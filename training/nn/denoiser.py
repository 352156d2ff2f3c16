"""Light diffusion denoiser (MSDNet Sec. III-D, Fig. 3) and the one DDIM update of the project.

The DDIM (eta = 0) update is written once, in :func:`ddim_update` (runtime/spec/ddim.py docstring,
step 5). Training calls it through :class:`DenoiserStep` / :func:`ddim_loop` (gradients flow), the
exporter folds it into ``denoiser_step.onnx``, and the runtime only feeds ``step_coefficients``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from msdnet.runtime.spec.ddim import alphas_cumprod
from msdnet.training.config import ModelConfig
from msdnet.training.nn.blocks import Bottleneck2d, TimeEmbedding, group_norm


def ddim_update(x_t: Tensor, eps: Tensor, abar_t: Tensor, abar_prev: Tensor) -> Tensor:
    """One deterministic DDIM step (eta = 0).

    x_t, eps: (B, C, H, W); abar_t, abar_prev: (1,) or (B,) float32 cumulative alphas.
    x0 = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t); x_prev = sqrt(abar_prev) x0 + sqrt(1 - abar_prev) eps.
    """
    a_t = abar_t.reshape(-1, 1, 1, 1)  # (1 | B, 1, 1, 1) broadcast over (B, C, H, W)
    a_prev = abar_prev.reshape(-1, 1, 1, 1)
    x0 = (x_t - torch.sqrt(1.0 - a_t) * eps) / torch.sqrt(a_t)
    return torch.sqrt(a_prev) * x0 + torch.sqrt(1.0 - a_prev) * eps


class LightDenoiser(nn.Module):
    """eps-prediction network: (x_t (B, C, H, W), t (B,) or (1,) float32 step) -> eps_hat (B, C, H, W).

    The time embedding is projected to C and added per channel, then two residual bottlenecks
    (C -> cfg.denoiser_hidden -> C) and an output head (GroupNorm, SiLU, 1x1 conv). The head is
    pointwise because it runs T_m times per frame: a 3x3 head (C x C x 9) would cost more than both
    bottlenecks together; the bottlenecks' 3x3 convs
    already give each step a 5x5 receptive field.

    Output: ``eps_hat = sqrt(1 - abar_t) x_t + head(...)``, the head zero-initialised. On unit-
    variance latents (training/models/latent.py) ``sqrt(1 - abar_t) x_t`` is the best linear guess of eps
    (its MSE is abar_t), so the network learns only what the latent structure adds; without this
    skip the light denoiser stays above the linear guess's error (docs/training.md).
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c, e = cfg.bev_channels, cfg.time_embed_dim
        self.time_embed = TimeEmbedding(e)
        self.time_proj = nn.Linear(e, c)
        self.blocks = nn.Sequential(
            Bottleneck2d(c, cfg.denoiser_hidden), Bottleneck2d(c, cfg.denoiser_hidden)
        )
        self.head = nn.Sequential(group_norm(c), nn.SiLU(), nn.Conv2d(c, c, 1))
        nn.init.zeros_(self.head[2].weight)
        nn.init.zeros_(self.head[2].bias)
        noise_scale = np.sqrt(1.0 - alphas_cumprod(cfg.diffusion)).astype(np.float32)  # (T + 1,)
        self.register_buffer("noise_scale", torch.tensor(noise_scale), persistent=False)

    def forward(self, x_t: Tensor, t: Tensor) -> Tensor:
        emb = self.time_proj(self.time_embed(t))  # (B | 1, C)
        h = x_t + emb[:, :, None, None]  # fused per channel
        skip = self.noise_scale[t.long()].reshape(-1, 1, 1, 1) * x_t  # sqrt(1 - abar_t) x_t
        return skip + self.head(self.blocks(h))


class DenoiserStep(nn.Module):
    """One DDIM step with the denoiser inside: what ``denoiser_step.onnx`` computes.

    forward(x_t (B, C, H, W), t (1,), abar_t (1,), abar_prev (1,)) -> x_prev (B, C, H, W);
    t, abar_t, abar_prev are one row of ``runtime.spec.ddim.step_coefficients`` (float32).
    """

    def __init__(self, denoiser: nn.Module) -> None:
        super().__init__()
        self.denoiser = denoiser

    def forward(self, x_t: Tensor, t: Tensor, abar_t: Tensor, abar_prev: Tensor) -> Tensor:
        return ddim_update(x_t, self.denoiser(x_t, t), abar_t, abar_prev)


def ddim_loop(
    step: nn.Module | Sequence[Callable[..., Tensor]],
    x: Tensor,
    coeffs: np.ndarray | Tensor,
    cond: Tensor | None = None,
) -> Tensor:
    """Run DDIM steps in order; gradients flow through every step (training uses this).

    step: a :class:`DenoiserStep`, or an ``R2LDMStep`` when ``cond`` (B, C, H, W) is given (called
    as ``step(x, cond, t, abar_t, abar_prev)``), or one such callable per row of ``coeffs`` (the
    student's training loop, training/nn/grad_balance.py); x: (B, C, H, W) start sample; coeffs: (T_m, 3)
    float32 ``[t, abar_t, abar_prev]`` rows from ``runtime.spec.ddim.step_coefficients``.
    Returns x after the last step, (B, C, H, W).
    """
    rows = torch.as_tensor(coeffs).to(device=x.device, dtype=torch.float32)  # (T_m, 3)
    steps = step if isinstance(step, Sequence) else [step] * rows.shape[0]
    if len(steps) != rows.shape[0]:
        raise ValueError(f"{len(steps)} step callables for {rows.shape[0]} DDIM steps")
    for k in range(rows.shape[0]):
        t, a_t, a_prev = rows[k, 0:1], rows[k, 1:2], rows[k, 2:3]  # each (1,)
        x = steps[k](x, t, a_t, a_prev) if cond is None else steps[k](x, cond, t, a_t, a_prev)
    return x
