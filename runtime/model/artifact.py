"""An exported model folder: ``manifest.json`` plus the ONNX graphs it lists, checked before use.
The folder is a path or a shipped model's name (``astyx-lite``: ``runtime/model/shipped``).

Checks, in order, each failing with :class:`MsdnetError` naming the file and the cause:
the folder and manifest are real files (no symlinks), the manifest parses and has this
runtime's ``FORMAT_VERSION``, the graphs listed are exactly the ones the model kind needs
(``onnx_spec``), each is a plain file inside the folder whose size and sha256 match the
manifest, and none keeps tensors in external files. Only then are the bytes handed to
onnxruntime, so the file checked is the file run. The grid and the diffusion schedule are
checked here too (a ``sample_steps`` of 0 or a voxel size of 0 is the manifest's fault).

With ``trusted_key`` (a PEM ed25519 public key, ``runtime/model/signing``) the exact manifest bytes
parsed must carry a valid ``manifest.sig`` by that key; the sha256 entries then make every graph
authentic, not only intact.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.onnx_check import external_tensors, graph_inputs
from msdnet.runtime.model.shipped import find_model, shipped_names
from msdnet.runtime.spec.cosine_logsnr import sampler_settings
from msdnet.runtime.spec.ddim import DiffusionConfig, alphas_cumprod, timesteps
from msdnet.runtime.spec.grid import GridConfig
from msdnet.runtime.spec.range_threshold import RangeThresholds, range_thresholds_from

MANIFEST = "manifest.json"
MAX_MANIFEST_BYTES = 16 * 1024 * 1024  # a manifest is a few hundred kB at most
GRAPHS_BY_KIND: dict[str, tuple[onnx_spec.GraphSpec, ...]] = {
    "student": onnx_spec.MSDNET_GRAPHS,
    "r2ldm": onnx_spec.R2LDM_GRAPHS,
}


def file_digest(path: str | Path) -> tuple[int, str]:
    """(size in bytes, sha256 hex) of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)
            size += len(chunk)
    return size, h.hexdigest()


@dataclass(frozen=True)
class InputSpec:
    """What the encoder expects of a point cloud."""

    columns: tuple[str, ...]  # point columns fed to the voxelizer, in order (first three x y z)
    shift: np.ndarray  # (C,) float32 per-column shift (applied inside encoder.onnx; informative)
    scale: np.ndarray  # (C,) float32 per-column scale (idem: the runtime feeds raw voxel means)
    max_voxels: int  # voxel cap per frame (extra voxels are dropped by the voxelizer)


@dataclass(frozen=True)
class Artifact:
    """A checked model folder: manifest fields plus the verified graph bytes."""

    root: Path  # the artifact folder
    manifest: dict[str, Any]  # manifest.json as parsed
    kind: str  # "student" (MSDNet) or "r2ldm"
    grid: GridConfig  # voxel grid the model was trained on
    diffusion: DiffusionConfig  # schedule; start_step / sample_steps are this kind's defaults
    threshold: float  # default occupancy threshold for decoding
    inputs: InputSpec  # point columns and normalisation
    specs: tuple[onnx_spec.GraphSpec, ...]  # graph contracts of this kind, in pipeline order
    graphs: dict[str, bytes]  # file name -> verified ONNX bytes
    # half-scale occupancy gate of the coarse-to-fine head (recon_head_sparse.onnx); None: the
    # artifact has no calibrated gate and the runtime uses the dense recon_head.onnx
    gate: float | None = None
    # keep an input radar point as it is when the head's occupancy around its voxel reaches this
    # (manifest ``keep_radar_threshold``; ``decode.radar_confidence_*``); None: keep none
    keep_threshold: float | None = None
    # one decoding threshold per band of horizontal range (manifest ``range_thresholds``,
    # ``spec.range_threshold``); None: ``threshold`` everywhere
    range_thresholds: RangeThresholds | None = None


def _need(obj: dict[str, Any], key: str, where: Path, kind: type | tuple[type, ...]) -> Any:
    if not isinstance(obj, dict) or key not in obj:
        raise MsdnetError(where, f"manifest has no {key!r}")
    value = obj[key]
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise MsdnetError(where, f"manifest field {key!r} has the wrong type")
    return value


def _regular_file(path: Path, what: str) -> None:
    if path.is_symlink():
        raise MsdnetError(path, f"{what} is a symlink; refusing to follow it")
    if not path.is_file():
        raise MsdnetError(path, f"{what} is missing")


def read_manifest(root: str | Path, trusted_key: str | Path | None = None) -> dict[str, Any]:
    """Parse ``root/manifest.json`` (its signature first, with ``trusted_key``) and check its
    format version. ``root`` is a folder or a shipped model's name (``shipped.find_model``)."""
    root = find_model(root)
    if root.is_symlink():
        raise MsdnetError(root, "model folder is a symlink; refusing to follow it")
    if not root.is_dir():
        raise MsdnetError(
            root, f"model folder not found (shipped models, by name: {', '.join(shipped_names())})"
        )
    path = root / MANIFEST
    _regular_file(path, "manifest")
    if path.stat().st_size > MAX_MANIFEST_BYTES:
        raise MsdnetError(path, f"manifest larger than {MAX_MANIFEST_BYTES} bytes")
    data = path.read_bytes()
    if trusted_key is not None:
        from msdnet.runtime.model.signing import verify_bytes

        verify_bytes(data, root, trusted_key)
    try:
        manifest = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MsdnetError(path, f"not valid JSON ({err})") from err
    if not isinstance(manifest, dict):
        raise MsdnetError(path, "manifest is not a JSON object")
    version = manifest.get("format_version")
    if version != onnx_spec.FORMAT_VERSION:
        raise MsdnetError(
            path,
            f"format version {version!r} is not supported "
            f"(this runtime reads version {onnx_spec.FORMAT_VERSION}); re-export the model",
        )
    return manifest


def _check_graph(root: Path, entry: Any) -> tuple[str, bytes]:
    """Check one manifest graph entry against its file; return (file name, bytes)."""
    where = root / MANIFEST
    name = _need(entry, "file", where, str)
    if Path(name).name != name or name in ("", ".", ".."):
        raise MsdnetError(where, f"graph file {name!r} is not a plain file name")
    size = _need(entry, "bytes", where, int)
    digest = _need(entry, "sha256", where, str)
    path = root / name
    _regular_file(path, "graph file")
    actual = path.stat().st_size
    if actual != size:
        raise MsdnetError(name, f"size mismatch (manifest {size} bytes, file {actual} bytes)")
    data = path.read_bytes()
    got = hashlib.sha256(data).hexdigest()
    if got != digest:
        raise MsdnetError(name, f"sha256 mismatch (manifest {digest[:16]}..., file {got[:16]}...)")
    try:
        outside = external_tensors(data)
    except ValueError as err:
        raise MsdnetError(name, str(err)) from err
    if outside:
        raise MsdnetError(name, f"keeps tensors in external files ({', '.join(outside[:3])})")
    return name, data


def _check_encoder_form(
    where: Path, manifest: dict[str, Any], form: str, rulebook: onnx_spec.GraphSpec, graph: bytes
) -> None:
    """The manifest's ``encoder_form`` (absent: rulebook) must be the form of ``encoder.onnx``'s
    inputs; MsdnetError naming the field when the graph is in the other form."""
    got = graph_inputs(graph)
    forms = {f: onnx_spec.encoder_spec_of(rulebook, f).inputs for f in onnx_spec.ENCODER_FORMS}
    if got == forms[form]:
        return
    actual = next((f for f, inputs in forms.items() if inputs == got), None)
    if actual is None:
        return  # neither form: the graph contract check names the inputs
    said = f"encoder_form {form!r}" if "encoder_form" in manifest else "no encoder_form (the rulebook form)"
    raise MsdnetError(
        where,
        f"{said} disagrees with {onnx_spec.ENCODER.file}, whose inputs are the {actual} form's: "
        f'the manifest field must be "encoder_form": "{actual}"',
    )


def _input_spec(manifest: dict[str, Any], where: Path) -> InputSpec:
    block = _need(manifest, "input", where, dict)
    columns = tuple(_need(block, "columns", where, list))
    norm = _need(block, "normalisation", where, dict)
    shift = np.asarray(_need(norm, "shift", where, list), dtype=np.float32)
    scale = np.asarray(_need(norm, "scale", where, list), dtype=np.float32)
    if not columns or columns[:3] != ("x", "y", "z"):
        raise MsdnetError(where, f"input columns must start with x, y, z, got {list(columns)}")
    if shift.shape != (len(columns),) or scale.shape != (len(columns),) or np.any(scale == 0):
        raise MsdnetError(where, "normalisation needs one shift and one non-zero scale per column")
    max_voxels = _need(block, "max_voxels", where, int)
    if max_voxels < 1:
        raise MsdnetError(where, f"max_voxels must be >= 1, got {max_voxels}")
    return InputSpec(columns, shift, scale, max_voxels)


def _configs(manifest: dict[str, Any], where: Path) -> tuple[GridConfig, DiffusionConfig]:
    grid_d = _need(manifest, "grid", where, dict)
    diff_d = _need(manifest, "diffusion", where, dict)
    try:
        grid = GridConfig(
            point_range=tuple(float(v) for v in grid_d["point_range"]),  # type: ignore[arg-type]
            voxel_size=tuple(float(v) for v in grid_d["voxel_size"]),  # type: ignore[arg-type]
            fov_deg=float(grid_d["fov_deg"]),
        )
        diffusion = DiffusionConfig(
            num_train_steps=int(diff_d["num_train_steps"]),
            beta_start=float(diff_d["beta_start"]),
            beta_end=float(diff_d["beta_end"]),
            start_step=int(diff_d["start_step"]),
            sample_steps=int(diff_d["sample_steps"]),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise MsdnetError(where, f"grid or diffusion block is incomplete or invalid ({err})") from None
    try:
        timesteps(diffusion)  # the manifest's own T_m and m must make a schedule
    except ValueError as err:
        raise MsdnetError(where, f"diffusion block: {err}") from None
    if list(grid.shape_zyx) != list(grid_d.get("shape_zyx", [])):
        raise MsdnetError(where, f"grid shape {grid_d.get('shape_zyx')} != {list(grid.shape_zyx)}")
    stored = diff_d.get("alphas_cumprod")
    if stored is not None:
        ours = alphas_cumprod(diffusion)
        if len(stored) != len(ours) or not np.allclose(stored, ours, rtol=1e-9, atol=0.0):
            raise MsdnetError(where, "stored alphas_cumprod differ from this runtime's schedule")
    return grid, diffusion


def load_artifact(root: str | Path, trusted_key: str | Path | None = None) -> Artifact:
    """Read and check a model folder (see the module docstring); graphs come back as bytes.
    ``root``: a folder or a shipped model's name (``astyx-lite``); ``trusted_key``: refuse a
    manifest not signed by this ed25519 public key (PEM file)."""
    root = find_model(root)
    manifest = read_manifest(root, trusted_key)
    where = root / MANIFEST
    kind = _need(manifest, "model_kind", where, str)
    if kind not in GRAPHS_BY_KIND:
        raise MsdnetError(where, f"model kind {kind!r} is not one of {sorted(GRAPHS_BY_KIND)}")
    sampler = manifest.get("sampler")  # R2LDM as published: its own loop (runtime/spec/cosine_logsnr.py)
    if sampler is not None:
        try:
            sampler_settings(sampler)
        except ValueError as err:
            raise MsdnetError(where, str(err)) from None
    specs = onnx_spec.graphs_of(kind, sampler, GRAPHS_BY_KIND)
    entries = _need(manifest, "graphs", where, list)
    listed = [e.get("file") if isinstance(e, dict) else None for e in entries]
    optional = [s for s in onnx_spec.OPTIONAL_GRAPHS if s.file in listed]
    specs = (*specs, *optional)
    form = manifest.get("encoder_form", "rulebook")  # absent in manifests before the pair form
    if form not in onnx_spec.ENCODER_FORMS:
        raise MsdnetError(where, f"encoder_form {form!r} is not one of {', '.join(onnx_spec.ENCODER_FORMS)}")
    rulebook = next((s for s in specs if s.file == onnx_spec.ENCODER.file), None)
    specs = tuple(onnx_spec.encoder_spec_of(s, form) if s.file == "encoder.onnx" else s for s in specs)
    needed = [s.file for s in specs]
    if sorted(map(str, listed)) != sorted(needed):
        missing = sorted(set(needed) - set(map(str, listed)))
        detail = f"missing {missing}" if missing else f"unexpected {sorted(map(str, listed))}"
        raise MsdnetError(where, f"graph list does not match a {kind} model ({detail})")
    graphs = dict(_check_graph(root, e) for e in entries)
    if rulebook is not None:
        _check_encoder_form(where, manifest, form, rulebook, graphs[onnx_spec.ENCODER.file])
    threshold = float(_need(manifest, "threshold", where, (int, float)))
    if not (math.isfinite(threshold) and 0.0 < threshold < 1.0):
        raise MsdnetError(where, f"threshold {threshold} not in (0, 1)")
    grid, diffusion = _configs(manifest, where)
    gate = manifest.get("gate")
    if gate is not None:
        if not optional or not isinstance(gate, (int, float)) or not 0.0 <= gate < 1.0:
            raise MsdnetError(where, f"gate {gate!r} needs recon_head_sparse.onnx and a value in [0, 1)")
        gate = float(gate)
    keep = manifest.get("keep_radar_threshold")
    if keep is not None:
        if isinstance(keep, bool) or not isinstance(keep, (int, float)) or not 0.0 <= keep <= 1.0:
            raise MsdnetError(where, f"keep_radar_threshold {keep!r} must be a number in [0, 1]")
        keep = float(keep)
    bands = manifest.get("range_thresholds")
    if bands is not None:
        bands = range_thresholds_from(bands, where)
    return Artifact(
        root=root,
        manifest=manifest,
        kind=kind,
        grid=grid,
        diffusion=diffusion,
        threshold=threshold,
        inputs=_input_spec(manifest, where),
        specs=specs,
        graphs=graphs,
        gate=gate,
        keep_threshold=keep,
        range_thresholds=bands,
    )
