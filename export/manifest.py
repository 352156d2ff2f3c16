"""``manifest.json`` of an artifact folder: everything the runtime needs besides the graphs.

Keys (read back by :mod:`msdnet.runtime.model.artifact`):

- ``format_version``: ``onnx_spec.FORMAT_VERSION``; ``model_kind``: ``student`` | ``r2ldm``;
- ``config``: the full ``ModelConfig`` (``dataclasses.asdict``);
- ``grid``: point_range, voxel_size, fov_deg and the dense ``shape_zyx`` (D, H, W);
- ``diffusion``: linear beta schedule parameters, ``alphas_cumprod`` (T + 1 values), the start
  step m (``start_step``; T for R2LDM, which starts from pure noise), the interval n = m / T_m
  (``interval``) and the default step count T_m (``sample_steps``);
- ``threshold``: default occupancy threshold; ``gate``: the coarse-to-fine head's half-scale
  occupancy gate (``null``: not calibrated, the runtime decodes with the dense head);
- ``input``: point ``columns`` in order, the per-column ``normalisation`` (shift, scale; applied
  inside ``encoder.onnx``, so the runtime feeds raw voxel means), ``max_voxels`` and ``layout``
  (the ``.bin`` layout of the training data, ``runtime/io/layouts``; ``msdnet-infer``'s default);
- ``bev_shape``: (1, C, H, W) of every BEV map; ``opset``; ``versions`` (torch, onnx, ...);
- ``parameters``: per graph and in total;
- ``graphs``: per graph file: name, bytes, sha256, input and output names (the optional
  ``onnx_spec.OPTIONAL_GRAPHS`` when the folder has them);
- ``source``: the checkpoint exported; ``verification``: the ``--verify`` report, when run.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import onnx
import onnxruntime

from msdnet.runtime.io.layouts import layout_for_columns
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import GRAPHS_BY_KIND, MANIFEST, file_digest
from msdnet.runtime.spec.cosine_logsnr import SamplerSettings
from msdnet.runtime.spec.ddim import DiffusionConfig, alphas_cumprod
from msdnet.training.config import ModelConfig
from msdnet.training.models.assembly import bev_shape
from msdnet.training.recipe.checkpoint import versions as checkpoint_versions


def runtime_diffusion(cfg: ModelConfig, kind: str) -> DiffusionConfig:
    """The schedule the runtime samples with: MSDNet from m with T_m steps, R2LDM from T (pure
    noise) with ``r2ldm_sample_steps``."""
    if kind == "r2ldm":
        d = cfg.diffusion
        steps = cfg.published.sample_steps if cfg.r2ldm_recipe == "published" else cfg.r2ldm_sample_steps
        return dataclasses.replace(d, start_step=d.num_train_steps, sample_steps=steps)
    return cfg.diffusion


def published_sampler(cfg: ModelConfig, kind: str) -> dict[str, Any] | None:
    """The ``sampler`` block of R2LDM as published (its resampled cosine log-SNR DDIM loop,
    runtime/spec/cosine_logsnr.py); None for every other model."""
    if kind != "r2ldm" or cfg.r2ldm_recipe != "published":
        return None
    p = cfg.published
    return SamplerSettings(p.sample_steps, p.resample, p.logsnr_min, p.logsnr_max).to_json()


def versions() -> dict[str, str]:
    """Library versions recorded in the manifest: the checkpoint's, plus onnx and onnxruntime."""
    return {**checkpoint_versions(), "onnx": onnx.__version__, "onnxruntime": onnxruntime.__version__}


def build_manifest(
    folder: Path,
    kind: str,
    cfg: ModelConfig,
    params: dict[str, int],
    source: str,
    gate: float | None = None,
    encoder_form: str = "rulebook",
) -> dict[str, Any]:
    """The manifest of the graphs already written in ``folder`` (sizes and hashes read now), its
    encoder in ``encoder_form`` (recorded when it is not the rulebook form)."""
    diff = runtime_diffusion(cfg, kind)
    graphs = []
    optional = [s for s in onnx_spec.OPTIONAL_GRAPHS if (folder / s.file).is_file()]
    sampler = published_sampler(cfg, kind)
    for spec in (*onnx_spec.graphs_of(kind, sampler, GRAPHS_BY_KIND), *optional):
        spec = onnx_spec.encoder_spec_of(spec, encoder_form) if spec.file == onnx_spec.ENCODER.file else spec
        size, digest = file_digest(folder / spec.file)
        graphs.append(
            {
                "name": spec.file.removesuffix(".onnx"),
                "file": spec.file,
                "bytes": size,
                "sha256": digest,
                "inputs": list(spec.inputs),
                "outputs": list(spec.outputs),
            }
        )
    shift, scale = zip(*cfg.radar_feature_norm, strict=True)
    return {
        "format_version": onnx_spec.FORMAT_VERSION,
        "model_kind": kind,
        "config": dataclasses.asdict(cfg),
        "grid": {
            "point_range": list(cfg.grid.point_range),
            "voxel_size": list(cfg.grid.voxel_size),
            "fov_deg": cfg.grid.fov_deg,
            "shape_zyx": list(cfg.grid.shape_zyx),
        },
        "diffusion": {
            "schedule": "linear" if sampler is None else "unused: the sampler block's schedule",
            "num_train_steps": diff.num_train_steps,
            "beta_start": diff.beta_start,
            "beta_end": diff.beta_end,
            "start_step": diff.start_step,
            "interval": diff.start_step / diff.sample_steps,
            "sample_steps": diff.sample_steps,
            "alphas_cumprod": alphas_cumprod(diff).tolist(),
        },
        **({} if sampler is None else {"sampler": sampler}),
        **({} if encoder_form == "rulebook" else {"encoder_form": encoder_form}),  # runtime.engine.pairs
        "threshold": cfg.threshold,
        "gate": gate,
        "input": {
            "columns": list(cfg.radar_columns),
            "normalisation": {
                "shift": list(shift),
                "scale": list(scale),
                "applied": "inside encoder.onnx: (voxel mean - shift) / scale",
            },
            "max_voxels": cfg.max_voxels_radar,
            "layout": layout_for_columns(cfg.radar_columns),  # .bin layout of the training data
        },
        "bev_shape": [1, *bev_shape(cfg)],
        "opset": onnx_spec.OPSET,
        "versions": versions(),
        "parameters": {**params, "total": sum(params.values())},
        "graphs": graphs,
        "source": source,
    }


def write_manifest(folder: Path, manifest: dict[str, Any]) -> Path:
    """Write ``folder/manifest.json`` (the folder itself is published atomically later)."""
    path = folder / MANIFEST
    path.write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    return path
