"""``msdnet-infer --dataset``: densify the radar of a paired dataset and compare with its LiDAR.

Each frame's radar scan (radar frame) goes through the pipeline; the dense cloud is written like
the file mode writes it (``OUT/<frame id>.<format>``, columns ``x y z confidence``), and the
frame is scored against its LiDAR sweep the way ``msdnet-bench quality`` scores it: the LiDAR
cropped to the grid box and the radar's field of view with its ground removed, the radar and the
dense cloud cropped the same way (``benchmarks.quality.suite.crop_to_grid``). The summary says how much
denser and how much closer to the LiDAR the output is than the radar, and
``OUT/comparison.json`` keeps every frame's figures. With ``options.keep_radar`` (``--keep-radar``)
the output, and so every "dense" figure, is the model's points plus the radar points in the grid;
``comparison.json`` then says ``"keep_radar": true``. Every radar row the engine did not use is
counted per frame (``dropped_*``, ``pointcloud.DROP_REASONS``) and in the summary's total.

A frame that cannot be loaded or run (a broken file, a bad calibration) does not stop the run:
it is reported (``failed`` in ``comparison.json``, FAILED lines in the summary, exit 1) and the
other frames are scored. Single-scan VoD frames never need a pose file.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.pointcloud import DROP_REASONS
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.densify import DensifyOptions, densify
from msdnet.runtime.io.atomic import atomic_output
from msdnet.runtime.io.datasets import open_dataset
from msdnet.runtime.io.datasets.preprocess import preprocess_frame
from msdnet.runtime.io.files import DENSE_COLUMNS, write_dense
from msdnet.runtime.spec.grid import GridConfig

OUT_COLUMNS = DENSE_COLUMNS  # columns of every written cloud
FSCORE_AT = 0.5  # metres: the F-score threshold quoted in the summary
COMPARISON_FILE = "comparison.json"


@dataclass(frozen=True)
class FrameComparison:
    """One frame: points inside the grid box and field of view, and distances to the LiDAR."""

    frame: str  # dataset frame id
    radar_points: int  # radar points (cropped like the LiDAR reference)
    dense_points: int  # output points (cropped like the LiDAR reference)
    lidar_points: int  # LiDAR reference points (cropped, ground removed)
    radar_cd: float  # Chamfer distance radar <-> LiDAR, metres (nan if the radar is empty)
    dense_cd: float  # Chamfer distance output <-> LiDAR, metres (nan if the output is empty)
    radar_fscore: float  # F-score of the radar at FSCORE_AT metres
    dense_fscore: float  # F-score of the output at FSCORE_AT metres
    seconds: float  # pipeline time of the frame
    dropped_nonfinite: int = 0  # radar rows with NaN/Inf (pointcloud.DROP_REASONS)
    dropped_outside_grid: int = 0  # finite radar rows outside the grid box
    dropped_over_cap: int = 0  # radar rows in the voxels over the max_voxels cap


def compare_frame(
    frame_id: str, radar: np.ndarray, dense: np.ndarray, lidar: np.ndarray, grid: GridConfig, seconds: float
) -> FrameComparison:
    """Score radar and output (N, >=3) [x, y, z, ...] against the LiDAR (K, 3), radar frame."""
    from msdnet.runtime.metrics.cloud import chamfer_distance, fscore
    from msdnet.runtime.metrics.crop import crop_to_grid

    r, d = crop_to_grid(radar, grid), crop_to_grid(dense, grid)
    ref = np.asarray(lidar, dtype=np.float32)[:, :3]

    def cd(pred: np.ndarray) -> float:
        return chamfer_distance(pred, ref) if len(pred) and len(ref) else float("nan")

    def fs(pred: np.ndarray) -> float:
        return fscore(pred, ref, FSCORE_AT) if len(ref) else float("nan")

    return FrameComparison(
        frame_id, len(r), len(d), len(ref), cd(r), cd(d), fs(r), fs(d), round(float(seconds), 4)
    )


def _mean(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def summarize(rows: list[FrameComparison]) -> dict[str, float]:
    """Means over the frames (distances over frames where they are defined)."""
    return {k: _mean([getattr(r, k) for r in rows]) for k in asdict(rows[0]) if k != "frame"}


def summary_lines(rows: list[FrameComparison], model_name: str) -> list[str]:
    """The two headline lines: how much denser, how much closer to the LiDAR."""
    m = summarize(rows)
    dens = m["dense_points"] / m["radar_points"] if m["radar_points"] else float("inf")
    if np.isfinite(m["dense_cd"]) and m["dense_cd"] > 0:
        closer = f"{m['dense_cd']:.3f} m ({m['radar_cd'] / m['dense_cd']:.1f}x closer)"
    else:
        closer = "no output points (try a lower --threshold)"
    totals = {k: sum(getattr(r, k) for r in rows) for k in DROP_REASONS}
    dropped = ", ".join(f"{n} {DROP_REASONS[k]}" for k, n in totals.items() if n)
    tail = [f"  dropped: radar rows not used: {dropped}"] if dropped else []
    return [
        f"{len(rows)} frames, median {np.median([r.seconds for r in rows]):.3f} s/frame; "
        "per frame inside the grid and field of view:",
        f"  denser:  radar {m['radar_points']:.0f} points -> {model_name} {m['dense_points']:.0f} "
        f"({dens:.1f}x; LiDAR {m['lidar_points']:.0f})",
        f"  closer:  Chamfer distance to LiDAR {m['radar_cd']:.3f} m -> {closer}; "
        f"F-score@{FSCORE_AT:g} m {m['radar_fscore']:.2f} -> {m['dense_fscore']:.2f}",
        *tail,
    ]


def run_dataset(
    pipe: Pipeline,
    dataset: str,
    root: Path,
    out: Path,
    split: str | None,
    max_frames: int | None,
    options: DensifyOptions,
) -> tuple[list[FrameComparison], list[str]]:
    """Densify every frame of ``root`` (``split``, first ``max_frames``), write clouds, compare;
    -> (scored frames, one ``"<frame>: <cause>"`` line per frame that failed)."""
    ds = open_dataset(dataset, root, split=split)
    ids = ds.frame_ids[:max_frames] if max_frames else ds.frame_ids
    if not ids:
        raise MsdnetError(root, f"no frames in split {split!r}")
    rows: list[FrameComparison] = []
    failed: list[str] = []
    for fid in tqdm(ids, unit="frame", desc="msdnet-infer", disable=None):
        try:
            rows.append(_run_frame(pipe, ds, dataset, fid, out, options))
        except MsdnetError as err:  # one bad frame must not stop the run
            failed.append(f"{fid}: {err}")
        except Exception as err:
            failed.append(f"{fid}: {type(err).__name__}: {' '.join(str(err).split())[:200]}")
    if not rows:
        raise MsdnetError(root, f"every frame failed; first: {failed[0]}")
    with atomic_output(out / COMPARISON_FILE) as tmp:
        body: dict[str, Any] = {"summary": summarize(rows), "frames": [asdict(r) for r in rows]}
        if failed:
            body["failed"] = failed
        if options.keep_radar:
            body["keep_radar"] = True  # dense_* figures score model points + radar points
        Path(tmp).write_text(json.dumps(body, indent=1, allow_nan=True) + "\n")
    return rows, failed


def check_radar_columns(artifact: Any, dataset: str, root: Path, split: str | None) -> None:
    """The first frame's radar columns against the model's (``scans.check_columns``), before any
    work: a dataset the model cannot read stops in one line naming the shipped models that read it."""
    from msdnet.runtime.frontends.infer.scans import check_columns
    from msdnet.runtime.frontends.model_args import BUNDLED_MODEL

    ds = open_dataset(dataset, root, split=split)
    try:
        columns = ds.load(ds.frame_ids[0]).radar.columns
    except (MsdnetError, IndexError):
        return  # no frame, or a broken first frame: the run reports it
    check_columns(str(root), columns, artifact.root, artifact.inputs.columns, BUNDLED_MODEL.parent)


def _run_frame(
    pipe: Pipeline, ds: Any, dataset: str, fid: str, out: Path, options: DensifyOptions
) -> FrameComparison:
    """Load, densify, write and score one frame."""
    grid = pipe.artifact.grid
    frame = preprocess_frame(ds.load(fid), grid)
    start = time.perf_counter()
    res = densify(pipe, frame.radar, options)
    seconds = time.perf_counter() - start
    dst = out / f"{fid}.{options.fmt}"
    write_dense(dst, res.points, res.confidence, options.fmt)
    row = compare_frame(fid, frame.radar.xyz, res.points, frame.lidar.xyz, grid, seconds)
    if options.png:
        name = "R2LDM" if pipe.artifact.kind == "r2ldm" else "MSDNet"
        _picture(dst.with_suffix(".png"), frame, res.points, grid, f"{dataset} {fid}", name)
    return replace(row, **{k: int(res.stats[k]) for k in DROP_REASONS})


def _picture(target: Path, frame: Any, dense: np.ndarray, grid: GridConfig, title: str, name: str) -> None:
    """The ``--png`` picture of one frame: LiDAR, output and radar inside the grid box and field of
    view, the crop ``comparison.json`` counts in, so the legend's counts are that frame's row."""
    from msdnet.runtime.io.pictures import RADAR_COLOUR, Layer, render_bev
    from msdnet.runtime.metrics.crop import crop_to_grid

    layers = [
        Layer(crop_to_grid(frame.lidar.xyz, grid), "#222222", "LiDAR", "dots"),
        Layer(crop_to_grid(dense, grid), "#1f5fbf", f"{name} output", "voxels"),
        Layer(crop_to_grid(frame.radar.xyz, grid), RADAR_COLOUR, "radar", "radar"),
    ]
    note = "counts: points inside the grid box and field of view, as in comparison.json"
    render_bev(target, layers, grid, title, note)
