"""The models ``msdnet-bench latency`` times: exported MSDNet + R2LDM folders (and their torch twins).

- :func:`random_pair`: randomly initialised MSDNet student and R2LDM baseline of a preset (one
  shared teacher, so one shared head), exported to a folder. Latency does not depend on the weights
  except through the number of decoded points, which the caller fixes with a threshold.
- :func:`given_pair`: a user's ``msdnet-export`` folder (MSDNet) and optionally an R2LDM folder; a
  missing R2LDM is built at random on the same config. The torch model of the MSDNet folder is
  loaded from the checkpoint its manifest names as ``source`` when that still exists.
- :func:`int8_artifact`: a copy of an artifact whose step graph is statically quantized to INT8
  (onnxruntime QDQ, per-channel weights, calibrated on real loop states), manifest re-hashed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import MANIFEST, file_digest, load_artifact
from msdnet.training.config import ModelConfig

KINDS = ("msdnet", "r2ldm")  # result keys; artifact kinds "student" and "r2ldm"
QUANT_OPS = ("Conv", "MatMul", "Gemm")  # only the compute-bound ops are quantized


@dataclass(frozen=True, eq=False)
class BenchModel:
    """One exported model and, when available, the torch module with the same weights."""

    folder: Path  # artifact folder (manifest.json + graphs)
    kind: str  # artifact kind: "student" or "r2ldm"
    weights: str  # "random" (initialised here) or "given" (the user's exported folder)
    torch_model: torch.nn.Module | None  # same weights in torch (eval), None when unavailable
    params: int  # deployed parameters (manifest "parameters.total")


@dataclass(frozen=True, eq=False)
class ModelPair:
    """MSDNet and the R2LDM baseline on the same grid."""

    cfg: ModelConfig  # the MSDNet config (R2LDM shares grid, channels and schedule)
    msdnet: BenchModel  # the student
    r2ldm: BenchModel  # the baseline


def _export(
    model: torch.nn.Module, kind: str, cfg: ModelConfig, folder: Path, source: str, up: str | None = None
) -> int:
    """Export ``model`` into the new ``folder``, the head's up-sampling in form ``up``
    (``training.nn.head.Up2x``; None: the exporter's own); -> deployed parameter count."""
    from msdnet.export.graphs import export_all
    from msdnet.export.manifest import build_manifest, write_manifest
    from msdnet.training.nn.head import up_export_style

    folder.mkdir(parents=True)
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # tracing is many tiny ops: a spinning OpenMP pool only slows it
    try:
        with up_export_style(up) if up is not None else contextlib.nullcontext():
            params, _ = export_all(model, kind, cfg, folder)
    finally:
        torch.set_num_threads(before)
    write_manifest(folder, build_manifest(folder, kind, cfg, params, source))
    return int(sum(params.values()))


def random_pair(cfg: ModelConfig, folder: Path, seed: int = 0, up: str | None = None) -> ModelPair:
    """Random MSDNet and R2LDM of ``cfg`` exported to ``folder/msdnet`` and ``folder/r2ldm``
    (``up``: the heads' up-sampling form, ``depth_to_space`` = the older export form;
    None: the exporter's own)."""
    from msdnet.training.models.assembly import build_model

    torch.manual_seed(seed)
    student = build_model("student", cfg).eval()
    r2ldm = build_model("r2ldm", cfg, student.teacher).eval()
    out = []
    for name, kind, model in tqdm(
        [("msdnet", "student", student), ("r2ldm", "r2ldm", r2ldm)],
        desc="export random models",
        unit="model",
        disable=None,
    ):
        params = _export(model, kind, cfg, folder / name, f"random init, seed {seed}", up)
        out.append(BenchModel(folder / name, kind, "random", model, params))
    return ModelPair(cfg, out[0], out[1])


def manifest_config(folder: Path) -> ModelConfig:
    """The ModelConfig stored in an artifact's manifest (``config`` block)."""
    from msdnet.training.recipe.checkpoint import dataclass_from_dict

    manifest = load_artifact(folder).manifest
    if "config" not in manifest:
        raise MsdnetError(folder / MANIFEST, "manifest has no 'config' block")
    return dataclass_from_dict(ModelConfig, manifest["config"], where=str(folder / MANIFEST))


def _torch_twin(folder: Path) -> torch.nn.Module | None:
    """The torch model of an artifact, from the checkpoint its manifest names (None if gone)."""
    from msdnet.training.recipe.checkpoint import load_checkpoint

    source = load_artifact(folder).manifest.get("source")
    if not isinstance(source, str) or not Path(source).is_dir():
        return None
    try:
        model, _, _ = load_checkpoint(source)
    except MsdnetError:
        return None
    return model.eval()


def _given(folder: Path, kind: str) -> BenchModel:
    art = load_artifact(folder)
    if art.kind != kind:
        raise MsdnetError(folder, f"is a {art.kind} model, expected {kind}")
    params = int(art.manifest.get("parameters", {}).get("total", 0))
    return BenchModel(folder, kind, "given", _torch_twin(folder), params)


def given_pair(model: Path, r2ldm: Path | None, scratch: Path, seed: int = 0) -> ModelPair:
    """The user's MSDNet folder, with the given R2LDM folder or a random one on the same config."""
    from msdnet.training.models.assembly import build_model

    msdnet = _given(model, "student")
    cfg = manifest_config(model)
    if r2ldm is not None:
        base = _given(r2ldm, "r2ldm")
        if load_artifact(r2ldm).grid != cfg.grid:
            raise MsdnetError(r2ldm, "R2LDM grid differs from the MSDNet model's grid")
        return ModelPair(cfg, msdnet, base)
    torch.manual_seed(seed)
    net = build_model("r2ldm", cfg).eval()
    params = _export(net, "r2ldm", cfg, scratch / "r2ldm", f"random init, seed {seed}")
    return ModelPair(cfg, msdnet, BenchModel(scratch / "r2ldm", "r2ldm", "random", net, params))


class _StatesReader:
    """onnxruntime CalibrationDataReader over recorded step-graph feeds."""

    def __init__(self, feeds: Sequence[dict[str, np.ndarray]]) -> None:
        self._it: Iterator[dict[str, np.ndarray]] = iter(feeds)

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._it, None)


def quantize_step_graph(src: Path, dst: Path, feeds: Sequence[dict[str, np.ndarray]]) -> None:
    """Static INT8 (QDQ, per-channel int8 weights, uint8 activations, MinMax calibration on
    ``feeds``: step-graph inputs recorded along a real DDIM loop) of the ONNX file ``src``."""
    from onnxruntime.quantization import QuantFormat, QuantType, quant_pre_process, quantize_static

    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # the quantizer warns (root logger) per rank-1 constant
    try:
        with tempfile.TemporaryDirectory(dir=dst.parent) as tmp:
            pre = Path(tmp) / "pre.onnx"
            quant_pre_process(str(src), str(pre))
            quantize_static(
                str(pre),
                str(dst),
                _StatesReader(feeds),
                quant_format=QuantFormat.QDQ,
                per_channel=True,
                activation_type=QuantType.QUInt8,
                weight_type=QuantType.QInt8,
                op_types_to_quantize=list(QUANT_OPS),
            )
    finally:
        root.setLevel(level)


def int8_artifact(src: Path, dst: Path, feeds: Sequence[dict[str, np.ndarray]]) -> Path:
    """Copy the MSDNet artifact ``src`` to the new folder ``dst`` with an INT8 step graph; the
    manifest gets the new size / sha256 and a ``quantization`` block. -> ``dst``."""
    art = load_artifact(src)
    if art.kind != "student":
        raise MsdnetError(src, "INT8 step graph: only MSDNet (student) artifacts")
    dst.mkdir(parents=True)
    for spec in art.specs:
        if spec.file != onnx_spec.DENOISER_STEP.file:
            shutil.copyfile(src / spec.file, dst / spec.file)
    quantize_step_graph(src / onnx_spec.DENOISER_STEP.file, dst / onnx_spec.DENOISER_STEP.file, feeds)
    manifest: dict[str, Any] = json.loads(json.dumps(art.manifest))  # deep copy
    for entry in manifest["graphs"]:
        entry["bytes"], entry["sha256"] = file_digest(dst / entry["file"])
    manifest["quantization"] = {
        "graph": onnx_spec.DENOISER_STEP.file,
        "method": "onnxruntime quantize_static, QDQ, per-channel",
        "weights": "int8",
        "activations": "uint8",
        "ops": list(QUANT_OPS),
        "calibration": f"{len(feeds)} loop states (MinMax)",
    }
    write_json_atomic(dst / MANIFEST, manifest)
    return dst


def publish_temp(tmp: str | Path, path: Path) -> None:
    """Give the finished temporary file ``tmp`` the mode a plain open() would (umask), then rename
    it onto ``path`` in the same folder (atomic)."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o666 & ~mask)
    os.replace(tmp, path)


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file next to ``path``, then :func:`publish_temp` it."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        publish_temp(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def write_json_atomic(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    write_text_atomic(path, json.dumps(obj, indent=1) + "\n")


def preset_config(preset: str) -> ModelConfig:
    """The model preset by name (MsdnetError on an unknown one)."""
    from msdnet.training.config import MODEL_PRESETS

    if preset not in MODEL_PRESETS:
        raise MsdnetError("--preset", f"unknown preset {preset!r} (one of {', '.join(MODEL_PRESETS)})")
    return dataclasses.replace(MODEL_PRESETS[preset])
