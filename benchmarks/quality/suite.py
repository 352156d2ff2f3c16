"""Point-cloud quality of every method on the same frames (MSDNet Tables I and II).

For each frame of a dataset split: the frame is preprocessed on the models' grid
(``runtime.io.datasets.preprocess.preprocess_frame``: radar cropped to the grid box; the LiDAR reference
cropped to the grid box and the radar's field of view, ground removed, as the papers evaluate),
every method turns the radar scan into a cloud, that cloud is cropped exactly like the reference
(``runtime.metrics.crop.crop_to_grid``) and scored against it with ``runtime.metrics.cloud.score_frame``.
Tables hold the mean of each metric over the frames where it is defined (an empty prediction has no CD).

Objects: on a dataset with 3D box labels (Astyx: ``groundtruth_obj3d``), every method is also
scored per labelled object the LiDAR sees, and on the radar points it keeps
(``benchmarks.quality.objects``: hit@5, object CD, points per object, by class and range band;
radar kept).

``save``: every method's cloud of every frame as ``save/<method key>/<frame>.npy`` ((M, 3)
float32 [x, y, z], radar frame, metres), the reference as ``save/lidar/<frame>.npy`` and an
``index.json`` naming the methods, frames and grid, so other tools can score the same clouds.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msdnet.benchmarks.eval_methods import Method, primary
from msdnet.benchmarks.quality.columns import FSCORE_KEYS, PANEL_COLOURS
from msdnet.benchmarks.quality.objects import (
    ObjectTally,
    near_radar,
    objects_definition,
    scored_objects,
    summarize_objects,
)
from msdnet.benchmarks.quality.official import official_markdown, official_section
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.atomic import atomic_output
from msdnet.runtime.io.datasets import FrameDataset
from msdnet.runtime.io.datasets.preprocess import preprocess_frame
from msdnet.runtime.io.files import write_cloud
from msdnet.runtime.metrics.cloud import FSCORE_THRESHOLDS, FrameScores, score_frame
from msdnet.runtime.metrics.crop import crop_to_grid, xy_range
from msdnet.runtime.metrics.official import OfficialFrames
from msdnet.runtime.spec.grid import GridConfig

# summary metrics, in table order: name -> whether lower is better
METRICS: dict[str, bool] = {
    "cd": True,
    "cd_squared": True,
    "mhd": True,
    **{k: False for k in FSCORE_KEYS},
    "jsd": True,
    "mmd": True,
}
AGREEMENT_TOL = 0.01  # torch vs onnxruntime: largest relative difference of a mean metric
# MSDNet vs R2LDM relative margins of the MSDNet paper, percent (negative: lower is better)
MARGIN_BAR = {"cd": -15.0, "mhd": -66.0, **{k: 44.0 for k in FSCORE_KEYS}}
LIDAR_KEY = "lidar"  # --save folder of the reference clouds
METRIC_SETS = ("ours", "official", "both")  # --metrics: ours, the R2LDM authors' formulas, or both
# results.json per_object rows: frame, class, range band, cloud points in the grown box, object CD
# (m, null when not hit), LiDAR points in the grown box
OBJECT_ROW_KEYS = ("frame", "class", "range", "points", "object_cd", "lidar_points")


@dataclass
class QualityRun:
    """Per-frame scores of every method, and the clouds kept for pictures."""

    frame_ids: list[str]  # frames scored, in order
    scores: dict[str, list[FrameScores]]  # method name -> one FrameScores per frame
    pictures: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # frame -> name -> (M, 3)
    official: dict[str, OfficialFrames] = field(default_factory=dict)  # name -> the authors' formulas
    objects: dict[str, ObjectTally] = field(default_factory=dict)  # name -> object rows (labelled data)
    boxes: dict[str, list[np.ndarray]] = field(default_factory=dict)  # picture frame -> (4, 2) footprints


def pick_frames(frame_ids: list[str], max_frames: int | None) -> list[str]:
    """All ids, or ``max_frames`` of them spread evenly over the split (in order)."""
    if max_frames is None or max_frames >= len(frame_ids):
        return list(frame_ids)
    picks = sorted({int(i) for i in np.linspace(0, len(frame_ids) - 1, max_frames)})
    return [frame_ids[i] for i in picks]


def grid_dict(grid: GridConfig) -> dict[str, Any]:
    """The grid for results.json: point_range (m), voxel_size (m), fov_deg."""
    return {
        "point_range": list(grid.point_range),
        "voxel_size": list(grid.voxel_size),
        "fov_deg": grid.fov_deg,
    }


def _save_cloud(folder: Path, frame_id: str, xyz: np.ndarray) -> None:
    write_cloud(folder / f"{frame_id}.npy", PointCloud(xyz, ("x", "y", "z")))


def evaluate_quality(
    ds: FrameDataset,
    frame_ids: list[str],
    methods: list[Method],
    grid: GridConfig,
    seed: int = 0,
    save: Path | None = None,
    picture_ids: tuple[str, ...] = (),
    progress: bool = True,
    official: bool = False,
) -> QualityRun:
    """Score every method on every frame (module docstring); keep the clouds of ``picture_ids``;
    ``official``: also the R2LDM authors' formulas (``quality.official``)."""
    run = QualityRun(list(frame_ids), {m.name: [] for m in methods})
    if official:
        run.official = {m.name: OfficialFrames() for m in methods}
    labelled = bool(getattr(ds, "has_boxes", False))  # the dataset reads 3D boxes (``ds.boxes``)
    if labelled:
        run.objects = {m.name: ObjectTally() for m in methods}
    area = xy_range(grid)
    for fid in tqdm(frame_ids, desc="quality", unit="frame", disable=not progress or None):
        frame = preprocess_frame(ds.get(fid), grid)
        ref = crop_to_grid(frame.lidar.xyz, grid)  # already cropped; a no-op kept for symmetry
        if save is not None:
            _save_cloud(save / LIDAR_KEY, fid, ref)
        kept: dict[str, np.ndarray] = {}
        if labelled:
            objs = scored_objects(ds.boxes(fid), ref, grid)  # type: ignore[attr-defined]
            near = near_radar(crop_to_grid(frame.radar.xyz, grid), ref)
            if fid in picture_ids:
                run.boxes[fid] = [objs.boxes.corners_bev(k) for k in range(len(objs))]
        for m in methods:
            pred = crop_to_grid(m.run(frame.lidar if m.input == "lidar" else frame.radar, seed), grid)
            run.scores[m.name].append(score_frame(pred, ref, area))
            if official:
                run.official[m.name].add(pred, ref)
            if labelled:
                run.objects[m.name].add(fid, objs, pred, near)
            if save is not None:
                _save_cloud(save / m.key, fid, pred)
            if fid in picture_ids:
                kept[m.name] = pred
        if fid in picture_ids:
            run.pictures[fid] = {**kept, "LiDAR": ref}
    return run


def _mean(values: list[float]) -> float:
    arr = np.asarray(values, dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    return float(arr.mean()) if arr.size else float("nan")


def frame_row(s: FrameScores) -> dict[str, float]:
    """One frame's scores as {metric: value} (``METRICS`` keys plus ``points``)."""
    return {
        "cd": s.cd,
        "cd_squared": s.cd_squared,
        "mhd": s.mhd,
        **{k: s.fscore[t] for k, t in zip(FSCORE_KEYS, FSCORE_THRESHOLDS, strict=True)},
        "jsd": s.jsd,
        "mmd": s.mmd,
        "points": float(s.num_points),
    }


def summarize(scores: list[FrameScores]) -> dict[str, float]:
    """Mean of each metric over the frames where it is finite; ``points`` mean points per frame;
    ``frames`` scored and ``empty_frames`` (no predicted point, so no CD / MHD / JSD / MMD)."""
    rows = [frame_row(s) for s in scores]
    out = {k: _mean([r[k] for r in rows]) for k in (*METRICS, "points")}
    out["frames"] = len(scores)
    out["empty_frames"] = sum(s.num_points == 0 for s in scores)
    return out


def relative_difference(a: float, b: float) -> float:
    """|a - b| / max(|a|, |b|) (0 when both are 0, nan when either is not finite)."""
    if not (math.isfinite(a) and math.isfinite(b)):
        return float("nan")
    scale = max(abs(a), abs(b))
    return abs(a - b) / scale if scale > 0 else 0.0


def agreement(summary: dict[str, dict[str, float]], methods: list[Method]) -> list[dict[str, Any]]:
    """torch vs onnxruntime of the same model kind (ablations are not paired): the largest
    relative difference of any mean metric (and points per frame); ``ok`` within ``AGREEMENT_TOL``."""
    rows = []
    for t in (m for m in methods if m.backend == "torch" and m.role != "ablation"):
        onnx = [m for m in methods if m.backend == "onnxruntime" and m.kind == t.kind and m.role == t.role]
        if len(onnx) != 1:
            continue
        o = onnx[0]
        diffs = {k: relative_difference(summary[t.name][k], summary[o.name][k]) for k in (*METRICS, "points")}
        finite = [d for d in diffs.values() if math.isfinite(d)]
        worst = max(finite) if finite else float("nan")
        rows.append(
            {
                "torch": t.name,
                "onnxruntime": o.name,
                "relative_difference": diffs,
                "max_relative_difference": worst,
                "tolerance": AGREEMENT_TOL,
                "ok": bool(finite) and worst <= AGREEMENT_TOL,
            }
        )
    return rows


def margins(summary: dict[str, dict[str, float]], methods: list[Method]) -> dict[str, Any] | None:
    """MSDNet vs R2LDM, percent: ``100 (MSDNet - R2LDM) / R2LDM`` per metric, with the bar
    (``MARGIN_BAR``) and whether it is met; None without both models."""
    ms, r2 = primary(methods, "msdnet"), primary(methods, "r2ldm")
    if ms is None or r2 is None:
        return None
    rows = {}
    for k in METRICS:
        a, b = summary[ms.name][k], summary[r2.name][k]
        pct = 100.0 * (a - b) / abs(b) if math.isfinite(a) and math.isfinite(b) and b != 0 else float("nan")
        bar = MARGIN_BAR.get(k)
        met = None
        if bar is not None and math.isfinite(pct):
            met = pct <= bar if bar < 0 else pct >= bar
        rows[k] = {"percent": pct, "bar": bar, "met": met}
    return {"msdnet": ms.name, "r2ldm": r2.name, "metrics": rows}


def per_frame(run: QualityRun) -> dict[str, list[dict[str, Any]]]:
    """method name -> [{frame, cd, cd_squared, mhd, fscore@t..., jsd, mmd, points}, ...]."""
    return {
        name: [{"frame": fid, **frame_row(s)} for fid, s in zip(run.frame_ids, scores, strict=True)]
        for name, scores in run.scores.items()
    }


def write_save_index(save: Path, methods: list[Method], frame_ids: list[str], grid: GridConfig) -> Path:
    """``save/index.json``: what the saved clouds are (methods by key, frames, grid, layout)."""
    doc = {
        "layout": "<key>/<frame>.npy: (M, 3) float32 [x, y, z], radar frame, metres",
        "reference": {"key": LIDAR_KEY, "what": "preprocessed LiDAR (grid box + FOV, ground removed)"},
        "methods": [{"key": m.key, "name": m.name} for m in methods],
        "frames": frame_ids,
        "grid": grid_dict(grid),
    }
    target = save / "index.json"
    with atomic_output(target) as tmp:
        tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return target


def strip_panels(run: QualityRun, fid: str, methods: list[Method]) -> list[tuple[str, np.ndarray, str]]:
    """The picture strip of one frame: radar | R2LDM (each onnxruntime R2LDM row, e.g. as published
    and improved; else the torch one) | MSDNet | LiDAR (models present only)."""

    clouds = run.pictures[fid]
    panels = [("4D radar", clouds[methods[0].name], PANEL_COLOURS["radar"])]
    for role in ("r2ldm", "msdnet"):
        every = [m for m in methods if m.role == "r2ldm" and m.backend == "onnxruntime"]
        first = primary(methods, role)
        for m in every if role == "r2ldm" and every else ([first] if first is not None else []):
            panels.append((m.name, clouds[m.name], PANEL_COLOURS[role]))
    panels.append(("LiDAR", clouds["LiDAR"], PANEL_COLOURS["lidar"]))
    return panels


def run_quality(
    ds: FrameDataset,
    evaluation: dict[str, Any],
    methods: list[Method],
    grid: GridConfig,
    out: Path,
    max_frames: int | None = None,
    seed: int = 0,
    pictures: int = 3,
    save: Path | None = None,
    progress: bool = True,
    metrics: str = "ours",
) -> dict[str, Any]:
    """Score ``methods`` (the first one raw radar) on ``ds`` and write ``out/results.json``,
    ``out/results.md`` and ``out/pictures/<frame>.png``; returns results.json's content.

    ``evaluation``: what was evaluated ({dataset, data, split}), copied into results.json.
    """
    from msdnet.benchmarks.machine import machine_info
    from msdnet.benchmarks.quality.report import picture_strip, quality_markdown, write_json, write_text

    frame_ids = pick_frames(list(ds.frame_ids), max_frames)
    if not frame_ids:
        raise MsdnetError(ds.root, f"split {evaluation.get('split')!r} has no frames")
    picture_ids = tuple(pick_frames(frame_ids, pictures)) if pictures > 0 else ()
    if metrics not in METRIC_SETS:
        raise MsdnetError("--metrics", f"must be one of {', '.join(METRIC_SETS)}, got {metrics!r}")
    official = metrics != "ours"
    run = evaluate_quality(ds, frame_ids, methods, grid, seed, save, picture_ids, progress, official)
    summary = {name: summarize(scores) for name, scores in run.scores.items()}
    out.mkdir(parents=True, exist_ok=True)
    pics = {}
    for fid in picture_ids:
        target = out / "pictures" / f"{fid}.png"
        title = f"{evaluation['dataset']} frame {fid}"
        picture_strip(target, strip_panels(run, fid, methods), grid, title, boxes=run.boxes.get(fid, ()))
        pics[fid] = str(target.relative_to(out))
    if save is not None:
        write_save_index(save, methods, frame_ids, grid)
    doc = {
        "evaluation": {
            **evaluation,
            "frames": len(frame_ids),
            "frame_ids": frame_ids,
            "seed": seed,
            "reference": "preprocessed LiDAR (grid box + field of view, ground removed)",
            "grid": grid_dict(grid),
            "saved_clouds": None if save is None else str(save),
            "metrics": metrics,
        },
        "machine": machine_info(sgemm=False).to_json(),
        "methods": [m.describe() for m in methods],
        "summary": summary,
        "agreement": agreement(summary, methods),
        "margins": margins(summary, methods),
        "pictures": pics,
        "per_frame": per_frame(run),
    }
    if official:
        doc["official"] = official_section(run.official, summary, methods)
    if run.objects:
        doc["objects"] = {
            "definition": objects_definition(),
            "summary": {name: summarize_objects(t) for name, t in run.objects.items()},
            "per_object": {
                name: [dict(zip(OBJECT_ROW_KEYS, r, strict=True)) for r in t.rows]
                for name, t in run.objects.items()
            },
        }
    write_json(out / "results.json", doc)
    text = quality_markdown(doc) if metrics != "official" else f"# Point-cloud quality: {evaluation}\n"
    if official:
        text += "\n".join(official_markdown(doc)) + "\n"
    write_text(out / "results.md", text)
    return doc
