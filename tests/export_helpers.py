"""Tiny random-initialised checkpoints and exported artifacts for the export/runtime tests.

The head's occupancy prior is set to 0.5 so an untrained tiny model still outputs thousands of
points (about half of the 10 240 tiny-grid voxels), which makes point comparisons meaningful.
Artifacts are built once per (kind, dataset) and per test process.
"""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
from collections.abc import Iterator
from pathlib import Path

import torch

from msdnet.export.graphs import export_all
from msdnet.export.manifest import build_manifest, write_manifest
from msdnet.training.config import MODEL_PRESETS, ModelConfig, TrainConfig
from msdnet.training.data.datasets import config_for_dataset
from msdnet.training.models.assembly import build_model
from msdnet.training.recipe.checkpoint import CheckpointState, save_checkpoint

_CACHE: dict[tuple[str, str], Path] = {}


@contextlib.contextmanager
def one_torch_thread() -> Iterator[None]:
    """torch's OpenMP pool on a shared 2-core machine costs ~1000x on tiny ops: use one thread."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def tiny_config(dataset: str = "vod") -> ModelConfig:
    """The tiny preset with the dataset's radar columns and an occupancy prior of 0.5."""
    cfg = config_for_dataset(MODEL_PRESETS["tiny"], dataset)
    return dataclasses.replace(cfg, occupancy_prior=0.5)


def make_checkpoint(folder: Path, kind: str, dataset: str = "vod", seed: int = 0) -> Path:
    """A random-initialised tiny ``kind`` checkpoint at ``folder``."""
    torch.manual_seed(seed)
    cfg = tiny_config(dataset)
    with one_torch_thread():
        model = build_model(kind, cfg)
    save_checkpoint(folder, model, cfg, CheckpointState(kind=kind, train=TrainConfig(), epochs=1))
    return folder


def make_artifact(root: Path, kind: str, dataset: str = "vod", head_kind: str = "dense") -> Path:
    """An exported tiny artifact (no verification), built once per process; ``root`` is a
    session-scoped temporary folder."""
    key = (kind, dataset, head_kind)
    if key not in _CACHE:
        torch.manual_seed(0)
        cfg = dataclasses.replace(tiny_config(dataset), head_kind=head_kind)
        model = build_model(kind, cfg).eval()
        folder = root / f"artifact-{kind}-{dataset}-{head_kind}"
        folder.mkdir(parents=True)
        with one_torch_thread():
            params, _ = export_all(model, kind, cfg, folder)
        write_manifest(folder, build_manifest(folder, kind, cfg, params, "tests"))
        _CACHE[key] = folder
    return _CACHE[key]


def make_exported_checkpoint(
    root: Path, dataset: str = "vod", threshold: float | None = None
) -> tuple[Path, Path]:
    """(checkpoint, artifact exported from it): a tiny random student; ``threshold`` (when given)
    goes into the manifest only, as ``msdnet-export --threshold`` does. The manifest's source names
    the checkpoint."""
    from msdnet.export.cli import export_model
    from msdnet.training.recipe.checkpoint import load_checkpoint

    ckpt = make_checkpoint(root / "ckpt", "student", dataset)
    model, cfg, _ = load_checkpoint(ckpt)
    if threshold is not None:
        cfg = dataclasses.replace(cfg, threshold=threshold)
    with one_torch_thread():
        export_model(model, "student", cfg, root / "onnx", str(ckpt))
    return ckpt, root / "onnx"


def copy_artifact(src: Path, dst: Path) -> Path:
    """A private copy of an artifact folder, to tamper with."""
    shutil.copytree(src, dst)
    return dst
