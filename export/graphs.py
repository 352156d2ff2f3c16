"""Torch modules for each ONNX graph of an artifact, example inputs, and the export call.

Each graph module's ``forward`` takes exactly the inputs of its ``onnx_spec`` contract, in
order, and returns its outputs in order, so names and dynamic axes come from one place:

- ``encoder.onnx``: the radar :class:`SparseEncoder` (its forward already follows the contract);
- ``rgfd_adapter.onnx``: :class:`RgfdAdapterGraph` = noise adapter after RGFD (Eq. 12);
- ``denoiser_step.onnx`` / ``r2ldm_step.onnx``: ``DenoiserStep`` / ``R2LDMStep`` (the DDIM update
  folded in; the runtime only feeds ``[t, abar_t, abar_prev]``);
- ``recon_head.onnx``: the reconstruction head at full scale, packed per half-scale voxel;
- ``recon_head_sparse.onnx``: :class:`SparseHeadGraph`, the coarse-to-fine head (full scale only
  under the half-scale voxels whose occupancy passes the gate; dynamic voxel count).
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import Tensor, nn

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.onnx_spec import GraphSpec
from msdnet.runtime.spec.ddim import step_coefficients
from msdnet.training.config import ModelConfig
from msdnet.training.data.batch import EncoderInput, make_encoder_input
from msdnet.training.models.assembly import bev_shape


class RgfdAdapterGraph(nn.Module):
    """(F_r^S (1, C, H, W), eps (1, C, H, W)) -> x_m = adapter(RGFD(F_r^S), eps) (1, C, H, W)."""

    def __init__(self, rgfd: nn.Module, adapter: nn.Module) -> None:
        super().__init__()
        self.rgfd = rgfd
        self.adapter = adapter

    def forward(self, bev_features: Tensor, noise: Tensor) -> Tensor:
        return self.adapter(self.rgfd(bev_features), noise)


class NoDgfdAdapterGraph(nn.Module):
    """The "w/o DGFD" ablation's ``rgfd_adapter.onnx``: F_r^R itself; eps is read (times 0) so
    the graph keeps the contract's inputs and the runtime runs it unchanged."""

    def __init__(self, rgfd: nn.Module) -> None:
        super().__init__()
        self.rgfd = rgfd

    def forward(self, bev_features: Tensor, noise: Tensor) -> Tensor:
        return self.rgfd(bev_features) + 0.0 * noise


class IdentityStepGraph(nn.Module):
    """The "w/o DGFD" ablation's ``denoiser_step.onnx``: x_prev = x_t (the loop changes nothing)."""

    def forward(self, x_t: Tensor, t: Tensor, abar_t: Tensor, abar_prev: Tensor) -> Tensor:
        return x_t + 0.0 * (t + abar_t + abar_prev)


class PackedHeadGraph(nn.Module):
    """``recon_head.onnx``: the head's full scale in the packed child layout (``ReconHead.packed``)."""

    def __init__(self, head: nn.Module) -> None:
        super().__init__()
        self.head = head

    def forward(self, features: Tensor) -> tuple[Tensor, Tensor]:
        return self.head.packed(features)


class SparseHeadGraph(nn.Module):
    """``recon_head_sparse.onnx``: the coarse-to-fine head (``ReconHead.sparse``)."""

    def __init__(self, head: nn.Module) -> None:
        super().__init__()
        self.head = head

    def forward(self, features: Tensor, gate: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return self.head.sparse(features, gate)


def graph_modules(model: nn.Module, kind: str) -> list[tuple[GraphSpec, nn.Module]]:
    """(contract, torch module) per graph of a ``student`` or ``r2ldm`` model, pipeline order."""
    if kind == "student" and not model.cfg.use_dgfd:  # ablation: same four graphs, loop = identity
        return [
            (onnx_spec.ENCODER, model.encoder),
            (onnx_spec.RGFD_ADAPTER, NoDgfdAdapterGraph(model.rgfd)),
            (onnx_spec.DENOISER_STEP, IdentityStepGraph()),
            (onnx_spec.RECON_HEAD, PackedHeadGraph(model.head)),
            (onnx_spec.RECON_HEAD_SPARSE, SparseHeadGraph(model.head)),
        ]
    if kind == "student":
        return [
            (onnx_spec.ENCODER, model.encoder),
            (onnx_spec.RGFD_ADAPTER, RgfdAdapterGraph(model.rgfd, model.adapter)),
            (onnx_spec.DENOISER_STEP, model.step),
            (onnx_spec.RECON_HEAD, PackedHeadGraph(model.head)),
            (onnx_spec.RECON_HEAD_SPARSE, SparseHeadGraph(model.head)),
        ]
    if kind == "r2ldm" and model.cfg.r2ldm_recipe == "published":  # training/models/r2ldm_published.py
        return [
            (onnx_spec.ENCODER_QUARTER, model.encoder),
            (onnx_spec.R2LDM_STEP, model.step),
            (onnx_spec.RECON_HEAD, PackedHeadGraph(model.head)),
            (onnx_spec.RECON_HEAD_SPARSE, SparseHeadGraph(model.head)),
        ]
    if kind == "r2ldm":
        return [
            (onnx_spec.ENCODER, model.encoder),
            (onnx_spec.R2LDM_STEP, model.step),
            (onnx_spec.RECON_HEAD, PackedHeadGraph(model.head)),
            (onnx_spec.RECON_HEAD_SPARSE, SparseHeadGraph(model.head)),
        ]
    raise MsdnetError(None, f"cannot export a {kind!r} model (only student and r2ldm)")


def count_parameters(module: nn.Module) -> int:
    """Scalar parameters of ``module`` (buffers excluded)."""
    return sum(p.numel() for p in module.parameters())


def tracing_points(cfg: ModelConfig, n: int = 400, seed: int = 0) -> np.ndarray:
    """(n, C) float32 random points spread over the grid box, columns ``cfg.radar_columns``
    (x y z uniform in the box; other columns ~ N(shift, scale) of the encoder normalisation)."""
    rng = np.random.default_rng(seed)
    lo = np.asarray(cfg.grid.point_range[:3], np.float64)
    hi = np.asarray(cfg.grid.point_range[3:], np.float64)
    pts = np.empty((n, len(cfg.radar_columns)), np.float64)
    pts[:, :3] = lo + (hi - lo) * rng.random((n, 3)) * 0.999
    for j, (shift, scale) in enumerate(cfg.radar_feature_norm[3:], start=3):
        pts[:, j] = shift + scale * rng.standard_normal(n)
    return pts.astype(np.float32)


def example_inputs(spec: GraphSpec, cfg: ModelConfig, enc: EncoderInput, seed: int = 0) -> tuple[Tensor, ...]:
    """Inputs of one graph, in contract order: the encoder's from ``enc``, random BEV maps
    (1, C, H, W) and the first DDIM row of the default schedule for the others."""
    g = torch.Generator().manual_seed(seed)
    shape = (1, *bev_shape(cfg))

    def bev() -> Tensor:
        return torch.randn(shape, generator=g)

    row = torch.from_numpy(step_coefficients(cfg.diffusion)[0])  # (3,) [t, abar_t, abar_prev]
    scalars = {"t": row[0:1], "abar_t": row[1:2], "abar_prev": row[2:3]}  # each (1,)
    scalars["gate"] = torch.zeros(1)  # the sparse head keeps every voxel while tracing
    if spec.file == onnx_spec.ENCODER.file:
        return encoder_tensors(enc, spec)
    return tuple(scalars[name] if name in scalars else bev() for name in spec.inputs)


def encoder_tensors(enc: EncoderInput, spec: GraphSpec) -> tuple[Tensor, ...]:
    """The encoder graph's inputs in ``spec`` order: ``enc.tensors()`` for ``ENCODER``; for
    ``ENCODER_QUARTER`` the levels 0..2 and the level-2 voxel coordinates as ``bev_coords``."""
    if spec is not onnx_spec.ENCODER_QUARTER:
        return enc.tensors()
    levels = (enc.subm[0], enc.down[0], enc.subm[1], enc.down[1], enc.subm[2])
    return (enc.features, *levels, enc.level_coords[2])


def export_graph(module: nn.Module, args: tuple[Tensor, ...], spec: GraphSpec, path: Path) -> None:
    """Trace ``module`` on ``args`` and write ``path`` (opset ``OPSET``, weights inside the file).

    The graph's inputs / outputs are named and made dynamic per ``spec``; the written model must
    pass ``onnx.checker`` and keep every tensor in the file.
    """
    buf = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # tracer warnings about Python-side shape arithmetic
        torch.onnx.export(
            module.eval(),
            args,
            buf,
            input_names=list(spec.inputs),
            output_names=list(spec.outputs),
            dynamic_axes=spec.dynamic_axes or None,
            opset_version=onnx_spec.OPSET,
            dynamo=False,
            do_constant_folding=True,
        )
    model = onnx.load_model_from_string(buf.getvalue())
    onnx.checker.check_model(model, full_check=True)
    names_in = tuple(i.name for i in model.graph.input)
    names_out = tuple(o.name for o in model.graph.output)
    if names_in != spec.inputs or names_out != spec.outputs:
        raise MsdnetError(spec.file, f"exported {names_in} -> {names_out}, contract {spec}")
    path.write_bytes(buf.getvalue())


def export_all(
    model: nn.Module, kind: str, cfg: ModelConfig, folder: Path, encoder_form: str = "rulebook"
) -> tuple[dict[str, int], EncoderInput]:
    """Write every graph of ``model`` into ``folder``, the encoder in ``encoder_form``
    (``onnx_spec.ENCODER_FORMS``: "pairs" is ``export.encoder_pairs``); -> (parameters per graph,
    traced input)."""
    if encoder_form not in onnx_spec.ENCODER_FORMS:
        known = ", ".join(onnx_spec.ENCODER_FORMS)
        raise MsdnetError("--encoder-form", f"{encoder_form!r} is not one of {known}")
    enc = make_encoder_input([tracing_points(cfg)], cfg.grid, cfg.max_voxels_radar)
    params: dict[str, int] = {}
    for spec, module in graph_modules(model, kind):
        export_graph(module, example_inputs(spec, cfg, enc), spec, folder / spec.file)
        if spec.file == onnx_spec.ENCODER.file and encoder_form == "pairs":
            from msdnet.export.encoder_pairs import pairs_encoder_model

            levels = sum(name.startswith("down_rules_") for name in spec.inputs)
            (folder / spec.file).write_bytes(pairs_encoder_model(module, levels).SerializeToString())
        if spec not in onnx_spec.OPTIONAL_GRAPHS:  # the sparse head's weights are recon_head's
            params[spec.file.removesuffix(".onnx")] = count_parameters(module)
    return params, enc
