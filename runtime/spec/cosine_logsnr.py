"""R2LDM as published: continuous-time cosine log-SNR schedule and the resampled DDIM plan.

Pure numpy, no I/O. R2LDM's paper writes the diffusion as a discrete chain (its Eq. 1, forward
``q(f_t | f_{t-1})``; Eq. 2, reverse ``p_theta(f_{t-1} | f_t)``) and the stage-2 loss as an L2
(Eq. 4). The authors' public code instead runs continuous time ``t in [0, 1]`` (variational
diffusion style), and that is what this module follows:

1. log-SNR, cosine: ``lambda(t) = -2 log tan(a + t (b - a))`` with ``a = atan(exp(-lambda_max / 2))``,
   ``b = atan(exp(-lambda_min / 2))``, so ``lambda(0) = lambda_max = 15``, ``lambda(1) = lambda_min = -15``.
2. ``alpha^2 = sigmoid(lambda)``, ``sigma^2 = sigmoid(-lambda)`` (variance preserving);
   forward (Eq. 1 in closed form): ``f_t = alpha_t f_0 + sigma_t eps``.
3. Loss weight of eps-prediction with min-SNR-gamma (gamma = 5): ``w(t) = min(SNR, gamma) / SNR``,
   ``SNR = exp(lambda)``; the Eq. 4 L2 is taken on eps, per sample mean, times ``w``.
4. DDIM, eta = 0 (Eq. 2 made deterministic), x0 clipped to [-1, 1]:
   ``x0 = clip((x_t - sigma_t eps) / alpha_t)``, ``eps' = (x_t - alpha_t x0) / sigma_t``,
   ``x_s = alpha_s x0 + sigma_s eps'``. The step graph takes ``[lambda_t, abar_t = alpha_t^2,
   abar_s = alpha_s^2]`` (the same three scalars as the linear-schedule step graph).
5. Resampling (RePaint style, jump length 1, ``R`` repeats): on the grid ``t_i = 1 - i / N``,
   step i is ``t_i -> t_{i+1}``; after each of its first ``R - 1`` runs the sample is re-noised
   back to ``t_i`` with ``q(x_t | x_s)``: ``x_t = (alpha_t / alpha_s) x_s + sqrt(sigma_t^2 -
   (alpha_t / alpha_s)^2 sigma_s^2) eps`` and the step is run again. The last step is not
   repeated: ``(N - 1) R + 1`` network calls (N = 128, R = 4: 509).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LOGSNR_MIN = -15.0  # lambda at t = 1 (pure noise end)
LOGSNR_MAX = 15.0  # lambda at t = 0 (data end)
MIN_SNR_GAMMA = 5.0  # min-SNR loss weighting
SAMPLER_NAME = "ddim_resampled_cosine_logsnr"  # the manifest's sampler.name for this plan


def log_snr(t: np.ndarray | float, lo: float = LOGSNR_MIN, hi: float = LOGSNR_MAX) -> np.ndarray:
    """Step 1: t (any shape, in [0, 1]) -> lambda(t) float64, same shape."""
    t_min = math.atan(math.exp(-0.5 * hi))
    t_max = math.atan(math.exp(-0.5 * lo))
    return -2.0 * np.log(np.tan(t_min + np.asarray(t, np.float64) * (t_max - t_min)))


def alpha_sigma(lam: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Step 2: lambda -> (alpha, sigma), float64, ``alpha^2 + sigma^2 = 1``."""
    lam = np.asarray(lam, np.float64)
    return np.sqrt(1.0 / (1.0 + np.exp(-lam))), np.sqrt(1.0 / (1.0 + np.exp(lam)))


def min_snr_weight(lam: np.ndarray | float, gamma: float = MIN_SNR_GAMMA) -> np.ndarray:
    """Step 3: lambda -> eps-prediction loss weight ``min(exp(lambda), gamma) / exp(lambda)``."""
    snr = np.exp(np.asarray(lam, np.float64))
    return np.minimum(snr, gamma) / snr


def renoise_coefficients(lam_t: float, lam_s: float) -> tuple[float, float]:
    """Step 5: (a, b) of ``x_t = a x_s + b eps`` that re-noises from s (cleaner) back to t."""
    a_t, s_t = alpha_sigma(lam_t)
    a_s, s_s = alpha_sigma(lam_s)
    ratio = float(a_t / a_s)
    return ratio, float(np.sqrt(max(float(s_t**2 - ratio**2 * s_s**2), 0.0)))


@dataclass(frozen=True)
class SamplerPlan:
    """Every network call of one resampled DDIM run, in order."""

    # (K, 3) float32 [lambda_t, abar_t, abar_s] fed to the step graph for call k
    coefficients: np.ndarray
    # (K, 2) float32 [a, b]: after call k, x <- a x + b eps (fresh N(0, I)); NaN rows: no re-noise
    renoise: np.ndarray
    steps: int  # N: DDIM steps from t = 1 to t = 0
    resample: int  # R: runs of every step but the last


def sampler_plan(steps: int, resample: int, lo: float = LOGSNR_MIN, hi: float = LOGSNR_MAX) -> SamplerPlan:
    """Steps 4-5 for N = ``steps`` DDIM steps, each run R = ``resample`` times (1: plain DDIM)."""
    if steps < 1 or resample < 1:
        raise ValueError(f"steps and resample must be >= 1, got {steps}, {resample}")
    grid = np.linspace(1.0, 0.0, steps + 1)
    lam = log_snr(grid, lo, hi)
    abar = alpha_sigma(lam)[0] ** 2
    rows, renoise = [], []
    for i in range(steps):
        runs = 1 if i == steps - 1 else resample
        for j in range(runs):
            rows.append((lam[i], abar[i], abar[i + 1]))
            last = j == runs - 1
            renoise.append((np.nan, np.nan) if last else renoise_coefficients(lam[i], lam[i + 1]))
    return SamplerPlan(
        np.asarray(rows, np.float32), np.asarray(renoise, np.float32), int(steps), int(resample)
    )


@dataclass(frozen=True)
class SamplerSettings:
    """The manifest's ``sampler`` block: which plan the runtime's loop runs by default."""

    steps: int  # N: default DDIM steps
    resample: int  # R: runs of every step but the last
    logsnr_min: float  # lambda at t = 1
    logsnr_max: float  # lambda at t = 0

    def plan(self, steps: int | None = None) -> SamplerPlan:
        """:func:`sampler_plan` for ``steps`` (None: the manifest's N)."""
        return sampler_plan(
            self.steps if steps is None else int(steps), self.resample, self.logsnr_min, self.logsnr_max
        )

    def to_json(self) -> dict[str, object]:
        """The manifest block."""
        return {"name": SAMPLER_NAME, "steps": self.steps, "resample": self.resample,
                "logsnr_min": self.logsnr_min, "logsnr_max": self.logsnr_max}  # fmt: skip


def sampler_settings(block: object) -> SamplerSettings:
    """Parse and check a manifest ``sampler`` block; ValueError naming what is wrong."""
    if not isinstance(block, dict) or block.get("name") != SAMPLER_NAME:
        raise ValueError(f"sampler must be an object named {SAMPLER_NAME!r}")
    try:
        out = SamplerSettings(int(block["steps"]), int(block["resample"]), float(block["logsnr_min"]),
                              float(block["logsnr_max"]))  # fmt: skip
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"sampler block is incomplete or invalid ({err})") from None
    if out.steps < 1 or out.resample < 1 or not out.logsnr_min < out.logsnr_max:
        raise ValueError(f"sampler needs steps >= 1, resample >= 1 and logsnr_min < logsnr_max, got {block}")
    return out
