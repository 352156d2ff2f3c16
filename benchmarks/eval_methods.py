"""How each evaluated method turns one radar scan into the cloud that is scored.

Every method takes a preprocessed radar scan (:class:`PointCloud`, radar frame, metres, cropped to
the grid box) and returns ``(M, 3) float32 [x, y, z]`` in the radar frame:

- :class:`RawRadar`: the radar points themselves (the "4D radar" row of the papers' tables);
- :class:`PipelineMethod`: an exported artifact folder (MSDNet or R2LDM) run by the torch-free
  :class:`~msdnet.runtime.engine.pipeline.Pipeline` through onnxruntime;
- :class:`TorchMethod`: a training checkpoint run in torch eager (``model.predict``), with the
  same noise as the pipeline (``numpy.random.default_rng(seed)``, drawn in the BEV shape) and the
  same decoder, so torch and onnxruntime are compared on equal terms.

torch is imported only when a :class:`TorchMethod` is built, so the ONNX-only paths run without
it. Every model method of one evaluation must share one voxel grid (:func:`common_grid`).
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.engine.decode import decode_occupancy
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model.artifact import MANIFEST
from msdnet.runtime.spec.grid import GRID_PRESETS, GridConfig

# model kind -> name in the tables, and the role of its row
KIND_LABELS = {"student": "MSDNet", "r2ldm": "R2LDM", "teacher": "Teacher (LiDAR in)"}
PUBLISHED_LABEL = "R2LDM as published"  # the R2LDM of --recipe published (the authors' code)
ROLE_OF_KIND = {"student": "msdnet", "r2ldm": "r2ldm", "teacher": "teacher"}
# what a row stands for, in table order ("teacher": LiDAR -> teacher -> points, the student's ceiling)
ROLES = ("radar", "r2ldm", "msdnet", "ablation", "teacher", "lidar")


@dataclass(frozen=True)
class RunSettings:
    """Inference settings shared by every model method of one evaluation."""

    steps: int | None = None  # MSDNet DDIM steps T_m (None: the model's default)
    r2ldm_steps: int | None = None  # R2LDM DDIM steps (None: the model's default)
    threshold: float | None = None  # occupancy threshold (None: the model's default)
    threads: int | None = None  # onnxruntime intra-op / torch threads (None: library default)
    provider: str = "cpu"  # onnxruntime execution provider (short name)

    def steps_for(self, kind: str) -> int | None:
        """The step count for a model of ``kind`` (student or r2ldm)."""
        return self.r2ldm_steps if kind == "r2ldm" else self.steps


class Method:
    """A named way to produce a cloud from a radar scan (see the module docstring)."""

    name: str  # display name in tables, e.g. "MSDNet (onnxruntime)"
    key: str  # file-system-safe name (``--save`` folder), e.g. "msdnet-onnxruntime"
    role: str  # one of ROLES
    kind: str  # "radar", "student" or "r2ldm"
    backend: str  # "input", "onnxruntime" or "torch"
    source: str  # where it came from (folder or "input")
    grid: GridConfig | None  # the model's voxel grid (None for raw radar)
    input: str = "radar"  # which preprocessed cloud of the frame ``run`` takes: "radar" or "lidar"

    def run(self, radar: PointCloud, seed: int) -> np.ndarray:
        """radar: preprocessed scan (the LiDAR for ``input == "lidar"``) -> (M, 3) float32
        [x, y, z] radar frame, metres."""
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        """JSON-ready description for results.json."""
        return {
            "name": self.name,
            "key": self.key,
            "role": self.role,
            "kind": self.kind,
            "backend": self.backend,
            "source": self.source,
        }


class RawRadar(Method):
    """The radar scan as it is (x, y, z only)."""

    def __init__(self) -> None:
        self.name, self.key, self.role = "4D radar", "radar", "radar"
        self.kind, self.backend, self.source, self.grid = "radar", "input", "input", None

    def run(self, radar: PointCloud, seed: int) -> np.ndarray:
        return np.ascontiguousarray(radar.xyz, dtype=np.float32)


class PipelineMethod(Method):
    """An exported artifact folder run by the onnxruntime :class:`Pipeline`."""

    def __init__(
        self, folder: Path, settings: RunSettings, name: str | None = None, keep_radar: bool = False
    ) -> None:
        from msdnet.runtime.engine.pipeline import Pipeline

        self.pipe = Pipeline.from_dir(folder, provider=settings.provider, threads=settings.threads)
        self.kind = self.pipe.kind
        self.backend, self.source = "onnxruntime", str(folder)
        self.grid = self.pipe.artifact.grid
        self.role = "ablation" if name else ("msdnet" if self.kind == "student" else "r2ldm")
        published = self.pipe.sampler is not None  # R2LDM as published (its own sampler block)
        self.name = name or f"{PUBLISHED_LABEL if published else KIND_LABELS[self.kind]} (onnxruntime)"
        self.key = slug(self.name)
        self.steps = settings.steps_for(self.kind)
        self.threshold = settings.threshold
        self.keep_radar = keep_radar  # output = model points + the input radar points

    def run(self, radar: PointCloud, seed: int) -> np.ndarray:
        kw = {"steps": self.steps, "threshold": self.threshold, "seed": seed, "keep_radar": self.keep_radar}
        return self.pipe(radar, **kw).points

    def describe(self) -> dict[str, Any]:
        a = self.pipe.artifact
        steps = self.steps or a.diffusion.sample_steps
        thr = a.threshold if self.threshold is None else self.threshold
        out = {**super().describe(), "steps": steps, "threshold": thr, "columns": list(a.inputs.columns)}
        if self.threshold is None and a.range_thresholds is not None:  # what the pipeline decodes at
            out["range_thresholds"] = a.range_thresholds.to_json()
        if a.keep_threshold is not None:
            out["keep_radar_threshold"] = a.keep_threshold
        return out


class TorchMethod(Method):
    """A student or R2LDM training checkpoint run in torch eager, decoded like the pipeline; or a
    teacher checkpoint, which takes the frame's preprocessed LiDAR (the row "Teacher (LiDAR in)":
    the ceiling the student chases)."""

    def __init__(self, checkpoint: Path, settings: RunSettings, name: str | None = None) -> None:
        import torch

        from msdnet.training.models.assembly import bev_shape
        from msdnet.training.recipe.checkpoint import load_checkpoint

        if settings.threads is not None:
            torch.set_num_threads(settings.threads)
        model, cfg, state = load_checkpoint(checkpoint)
        self.model, self.cfg, self.kind = model, cfg, state.kind
        self.backend, self.source, self.grid = "torch", str(checkpoint), cfg.grid
        self.role = "ablation" if name else ROLE_OF_KIND[self.kind]
        published = getattr(cfg, "r2ldm_recipe", "improved") == "published" and self.kind == "r2ldm"
        self.name = name or f"{PUBLISHED_LABEL if published else KIND_LABELS[self.kind]} (torch)"
        self.input = "lidar" if self.kind == "teacher" else "radar"
        self.columns = cfg.lidar_columns if self.kind == "teacher" else cfg.radar_columns
        self.max_voxels = cfg.max_voxels_lidar if self.kind == "teacher" else cfg.max_voxels_radar
        self.key = slug(self.name)
        default = cfg.diffusion.sample_steps if self.kind == "student" else cfg.r2ldm_sample_steps
        if published:
            default = cfg.published.sample_steps
        self.steps = settings.steps_for(self.kind) or default
        self.threshold = cfg.threshold if settings.threshold is None else settings.threshold
        self.noise_shape = (1, *bev_shape(cfg))  # (1, C, H8, W8) like the pipeline's eps

    def run(self, radar: PointCloud, seed: int) -> np.ndarray:
        import torch

        from msdnet.training.data.batch import make_encoder_input

        pts = np.ascontiguousarray(radar.select(self.columns).points, dtype=np.float32)
        enc = make_encoder_input([pts], self.cfg.grid, self.max_voxels)
        if enc.features.shape[0] == 0:  # no voxel in the grid: the pipeline returns nothing too
            return np.empty((0, 3), np.float32)
        rng = np.random.default_rng(seed)  # x_T, then (published R2LDM) the re-noising draws
        noise = rng.standard_normal(self.noise_shape, dtype=np.float32)
        extra = {"rng": rng} if getattr(self.model, "takes_rng", False) else {}
        with torch.no_grad():
            if self.kind == "teacher":
                occ, off = self.model.predict(enc)
            else:
                occ, off = self.model.predict(
                    enc, noise=torch.from_numpy(noise), sample_steps=self.steps, **extra
                )
        points, _ = decode_occupancy(occ[0].numpy(), off[0].numpy(), self.cfg.grid, self.threshold)
        return points

    def describe(self) -> dict[str, Any]:
        return {
            **super().describe(),
            "steps": self.steps,
            "threshold": self.threshold,
            "columns": list(self.columns),
        }


def slug(name: str) -> str:
    """A file-system-safe lower-case name: "MSDNet (torch)" -> "msdnet-torch"."""
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "method"


def is_artifact(folder: Path) -> bool:
    """Whether ``folder`` is an exported artifact (holds manifest.json)."""
    return (Path(folder) / MANIFEST).is_file()


def open_model(path: Path, settings: RunSettings, name: str | None = None) -> Method:
    """An artifact folder -> :class:`PipelineMethod`; anything else is read as a checkpoint ->
    :class:`TorchMethod`. ``name`` (ablations) replaces the name derived from the model kind."""
    path = Path(path)
    if not path.exists():
        raise MsdnetError(path, "model folder not found")
    if is_artifact(path):
        return PipelineMethod(path, settings, name)
    return TorchMethod(path, settings, name)


def parse_ablation(text: str) -> tuple[str, Path]:
    """ "w/o RGFD=runs/no-rgfd" -> ("w/o RGFD", Path("runs/no-rgfd")); MsdnetError otherwise."""
    name, sep, folder = text.partition("=")
    if not sep or not name.strip() or not folder.strip():
        raise MsdnetError("--ablation", f"expected NAME=DIR, got {text!r}")
    return name.strip(), Path(folder.strip())


def build_methods(
    models: list[Path],
    checkpoints: list[Path],
    ablations: list[str],
    settings: RunSettings,
    keep_radar: bool = False,
) -> list[Method]:
    """Raw radar, ``models`` (artifact folders, onnxruntime), ``checkpoints`` (torch; a teacher
    checkpoint gives the LiDAR-in teacher row) and ``ablations`` (NAME=DIR, artifact or
    checkpoint), ordered by role (radar, R2LDM, MSDNet, ablations, teacher; onnxruntime before
    torch within a role). ``keep_radar`` adds a row "MSDNet + radar points" per MSDNet artifact.
    Repeated names get the folder name."""
    methods: list[Method] = [RawRadar()]
    for folder in models:
        if not is_artifact(folder):
            raise MsdnetError(folder, f"not an exported model folder (no {MANIFEST}); use --checkpoint")
        methods.append(PipelineMethod(folder, settings))
        if keep_radar and methods[-1].kind == "student":
            methods.append(PipelineMethod(folder, settings, "MSDNet + radar points (onnxruntime)", True))
    methods += [TorchMethod(path, settings) for path in checkpoints]
    methods += [open_model(folder, settings, name) for name, folder in map(parse_ablation, ablations)]
    methods.sort(key=lambda m: (ROLES.index(m.role), m.role != "ablation" and m.backend != "onnxruntime"))
    _make_unique(methods)
    if settings.threshold is None:
        adopt_export_thresholds(methods)
    return methods


def adopt_export_thresholds(methods: list[Method]) -> None:
    """A checkpoint evaluated beside its own export decodes at the export's threshold.

    ``msdnet-export --threshold/--calibrate`` records the decoding threshold in the manifest only;
    the checkpoint still holds the training one. The export's manifest names the checkpoint it
    came from (``source``), so torch and onnxruntime rows of the same model compare like for like.
    """
    exported: dict[Path, PipelineMethod] = {}
    for m in methods:
        if isinstance(m, PipelineMethod) and m.pipe.artifact.manifest.get("source"):
            exported[Path(m.pipe.artifact.manifest["source"]).resolve()] = m
    for m in methods:
        match = exported.get(Path(m.source).resolve()) if isinstance(m, TorchMethod) else None
        if match is not None:
            m.threshold = match.pipe.artifact.threshold
    # The teacher shares its head with the student: decode it at the MSDNet export's threshold.
    student = primary([m for m in methods if isinstance(m, PipelineMethod)], "msdnet")
    for m in methods:
        if isinstance(m, TorchMethod) and m.kind == "teacher" and student is not None:
            m.threshold = student.pipe.artifact.threshold


def _make_unique(methods: list[Method]) -> None:
    """Append the source folder name to model names that repeat; refuse names still equal;
    then make the keys unique with a counter."""
    counts = Counter(m.name for m in methods)
    for m in methods:
        named_by_us = m.role != "ablation" or getattr(m, "keep_radar", False)  # not a user's NAME=
        if counts[m.name] > 1 and named_by_us and m.name.endswith(")"):
            m.name = f"{m.name[:-1]}, {Path(m.source).name})"
    repeated = [name for name, n in Counter(m.name for m in methods).items() if n > 1]
    if repeated:
        raise MsdnetError(None, f"two methods are named {repeated[0]!r}; give distinct folders or names")
    keys: Counter[str] = Counter()
    for m in methods:
        keys[m.key] += 1
        if keys[m.key] > 1:
            m.key = f"{m.key}-{keys[m.key]}"


def common_grid(methods: list[Method], preset: str | None = None) -> GridConfig:
    """The one voxel grid of every model method (or ``GRID_PRESETS[preset]`` with none).

    MsdnetError when models disagree, or when ``preset`` contradicts them.
    """
    grids = [(m.grid, m.source) for m in methods if m.grid is not None]
    if not grids:
        return GRID_PRESETS[preset or "lite"]
    grid, source = grids[0]
    for other, where in grids[1:]:
        if other != grid:
            raise MsdnetError(where, f"voxel grid differs from {source}'s; score models on one grid")
    if preset is not None and GRID_PRESETS[preset] != grid:
        raise MsdnetError("--grid", f"preset {preset!r} differs from the models' grid")
    return grid


def primary(methods: list[Method], role: str) -> Method | None:
    """The method shown as MSDNet / R2LDM in margins and pictures: onnxruntime first, then torch."""
    found = [m for m in methods if m.role == role]
    found.sort(key=lambda m: m.backend != "onnxruntime")
    return found[0] if found else None
