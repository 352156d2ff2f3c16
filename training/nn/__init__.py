"""Dense 2D networks on BEV maps (B, C, H, W), C = cfg.bev_channels, H = W = grid / 8.

- :mod:`.deform`: ``DeformConv2d`` (pure torch, exports to ONNX ``DeformConv``)
- :mod:`.blocks`: CBAM, ConvNeXt block, bottleneck, time embedding, ``count_parameters``
- :mod:`.rgfd`: ``RGFD`` (F_r^S -> F_r^R)
- :mod:`.adapter`: ``NoiseAdapter`` ((F_r^R, eps) -> x_m)
- :mod:`.denoiser`: ``LightDenoiser``, ``DenoiserStep``, ``ddim_update``, ``ddim_loop``
- :mod:`.unet`: ``R2LDMUNet``, ``R2LDMStep`` (the R2LDM baseline)
"""

from __future__ import annotations

from msdnet.training.config import ModelConfig
from msdnet.training.nn.adapter import NoiseAdapter
from msdnet.training.nn.blocks import count_parameters
from msdnet.training.nn.deform import DeformConv2d
from msdnet.training.nn.denoiser import DenoiserStep, LightDenoiser, ddim_loop, ddim_update
from msdnet.training.nn.rgfd import RGFD
from msdnet.training.nn.unet import R2LDMStep, R2LDMUNet

__all__ = [
    "RGFD",
    "DeformConv2d",
    "DenoiserStep",
    "LightDenoiser",
    "NoiseAdapter",
    "R2LDMStep",
    "R2LDMUNet",
    "count_parameters",
    "ddim_loop",
    "ddim_update",
    "dense_parameter_counts",
]


def dense_parameter_counts(cfg: ModelConfig) -> dict[str, int]:
    """Parameters per dense module for one preset: rgfd, noise_adapter, light_denoiser, r2ldm_unet."""
    return {
        "rgfd": count_parameters(RGFD(cfg)),
        "noise_adapter": count_parameters(NoiseAdapter(cfg)),
        "light_denoiser": count_parameters(LightDenoiser(cfg)),
        "r2ldm_unet": count_parameters(R2LDMUNet(cfg)),
    }
