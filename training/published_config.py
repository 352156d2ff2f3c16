"""Settings of R2LDM as its authors published it (``msdnet-train ... --recipe published``).

Pure dataclasses (no torch), nested in :class:`~msdnet.training.config.ModelConfig` as
``ModelConfig.published``; used only when ``ModelConfig.r2ldm_recipe == "published"``. The
defaults are the published values except the U-Net width (``unet_base``), which is narrowed so
that it trains on a 2-core CPU (docs/training.md states both parameter counts).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

RECIPES = ("improved", "published")  # --recipe: ours | the authors' public code


@dataclass(frozen=True)
class PublishedR2LDMConfig:
    """Architecture, schedule and sampler of the published R2LDM."""

    latent_channels: int = 8  # channels of the latent at 1/4 of the grid (published: 4 x 2 heights)
    encoder_channels: tuple[int, int, int] = (4, 4, 4)  # sparse backbone width at 1, 1/2, 1/4 (published: 4)
    unet_base: int = 16  # U-Net base width (published: 64; narrowed to train on this CPU)
    unet_multipliers: tuple[int, int, int, int] = (1, 2, 4, 8)  # width per level, times unet_base
    unet_res_blocks: int = 3  # residual blocks per U-Net level (published: 3)
    unet_groups: int = 8  # GroupNorm groups of the U-Net (published: 8)
    unet_in_channels: int = 32  # width of the first convolution after concatenating latent + condition
    ring: bool = True  # circular padding along W in the U-Net convolutions (published: ring=True)
    logsnr_min: float = -15.0  # log-SNR at t = 1
    logsnr_max: float = 15.0  # log-SNR at t = 0
    min_snr_gamma: float = 5.0  # min-SNR loss weighting of the eps loss
    sample_steps: int = 128  # DDIM steps from t = 1 to 0
    resample: int = 4  # runs of each DDIM step (RePaint-style resampling, jump length 1)
    x0_clip: float = 1.0  # the sampler clips its x0 estimate to +-this
    offset_weight: float = 0.04  # LPCR stage: BCE + offset_weight * L1(offset), full scale


# Smaller published settings per preset (tests and smoke runs); "lite" and "paper" take the defaults.
PRESET_OVERRIDES: dict[str, dict[str, object]] = {
    "tiny": {"unet_base": 8, "unet_res_blocks": 1, "unet_in_channels": 16, "sample_steps": 4, "resample": 2},
}


def with_recipe(cfg: Any, recipe: str) -> Any:
    """``cfg`` (a ModelConfig) set to ``recipe``. "published" also takes the radar's x, y, z columns
    only (the published reader) and this preset's :data:`PRESET_OVERRIDES`."""
    if recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {RECIPES}, got {recipe!r}")
    if recipe == "improved":
        return replace(cfg, r2ldm_recipe=recipe)
    published = replace(cfg.published, **PRESET_OVERRIDES.get(cfg.preset, {}))
    xyz = ("x", "y", "z")
    return replace(cfg, r2ldm_recipe=recipe, published=published, radar_columns=xyz, radar_feature_norm=())


def published_train_config(tcfg: Any, kind: str) -> Any:
    """The published optimisation settings on a TrainConfig: batch 1, gradient clip 1.0, lr 1e-3
    (LPCR stage, kind "teacher") or 1e-4 (diffusion stage, "r2ldm"), EMA 0.995 of the weights
    when the training loop has one (``TrainConfig.ema_decay``)."""
    extra = {"ema_decay": 0.995} if hasattr(tcfg, "ema_decay") else {}
    return replace(tcfg, batch_size=1, grad_clip=1.0, lr=1e-3 if kind == "teacher" else 1e-4, **extra)
