"""Diffusion schedule for MSDNet's DDIM loop: pure numpy, no I/O.

Conventions (MSDNet Sec. III-D, DDIM with eta = 0):

1. Linear beta schedule over T steps (DDPM defaults ``beta_1 = 1e-4 ... beta_T = 0.02``).
2. ``alphas_cumprod[t] = prod_{s=1..t} (1 - beta_s)`` for ``t = 0..T``; index 0 is 1 (clean).
3. Forward noising, Eq. (9): ``x_t = sqrt(abar_t) x_0 + sqrt(1 - abar_t) eps``.
4. The student starts at step ``m`` (the noise adapter puts its features there, Eq. 12) and
   runs ``T_m`` steps down to 0: ``t_k = round(m - k m / T_m)``, ``k = 0..T_m-1``;
   with m = 500, T_m = 50 that is ``500, 490, ..., 10`` (interval n = 10, Eq. 13).
5. One DDIM update (written once, in the torch step module; the runtime feeds these
   coefficients): ``x0 = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t)``,
   ``x_prev = sqrt(abar_prev) x0 + sqrt(1 - abar_prev) eps``; after the last step
   ``abar_prev = abar_0 = 1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DiffusionConfig:
    """Diffusion hyper-parameters (MSDNet Sec. IV-B)."""

    num_train_steps: int = 1000  # T: length of the forward chain
    beta_start: float = 1e-4  # beta_1 of the linear schedule
    beta_end: float = 0.02  # beta_T of the linear schedule
    start_step: int = 500  # m: the step the noise adapter aligns the student features to
    sample_steps: int = 50  # T_m: DDIM steps from m to 0 (interval n = m / T_m)


def betas(cfg: DiffusionConfig) -> np.ndarray:
    """(T,) float64: beta_1 .. beta_T (step 1)."""
    return np.linspace(cfg.beta_start, cfg.beta_end, cfg.num_train_steps, dtype=np.float64)


def alphas_cumprod(cfg: DiffusionConfig) -> np.ndarray:
    """(T + 1,) float64: abar_0 = 1, abar_t = prod_{s<=t} (1 - beta_s) (step 2)."""
    return np.concatenate([[1.0], np.cumprod(1.0 - betas(cfg))])


def timesteps(cfg: DiffusionConfig, sample_steps: int | None = None, start: int | None = None) -> np.ndarray:
    """(T_m,) int64: the DDIM steps from ``start`` (default m) down to (not including) 0 (step 4)."""
    m = cfg.start_step if start is None else int(start)
    n_steps = cfg.sample_steps if sample_steps is None else int(sample_steps)
    if n_steps < 1:
        raise ValueError(f"sample_steps must be >= 1, got {n_steps}")
    if not 1 <= m <= cfg.num_train_steps:
        raise ValueError(f"start step must be in 1..{cfg.num_train_steps}, got {m}")
    if n_steps > m:
        raise ValueError(f"sample_steps ({n_steps}) cannot exceed the start step ({m})")
    return np.round(np.linspace(m, 0, n_steps + 1)[:-1]).astype(np.int64)


def step_coefficients(
    cfg: DiffusionConfig, sample_steps: int | None = None, start: int | None = None
) -> np.ndarray:
    """(T_m, 3) float32 ``[t, abar_t, abar_prev]`` for each DDIM step in order (step 5)."""
    ts = timesteps(cfg, sample_steps, start)
    abar = alphas_cumprod(cfg)
    prev = np.concatenate([ts[1:], [0]])
    return np.stack([ts.astype(np.float64), abar[ts], abar[prev]], axis=1).astype(np.float32)


def q_sample(x0: np.ndarray, t: int, noise: np.ndarray, cfg: DiffusionConfig) -> np.ndarray:
    """Eq. (9): x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) noise (step 3); noise passed in."""
    a = alphas_cumprod(cfg)[t]
    return (np.sqrt(a) * x0 + np.sqrt(1.0 - a) * noise).astype(x0.dtype)
