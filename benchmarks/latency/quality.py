"""Quality beside latency (MSDNet Table III): the metrics of a model's output at each step count.

Frames come from a dataset folder (``vod``, ``astyx`` or ``sim`` layout), preprocessed as for
training (LiDAR cropped to the grid box and the radar's field of view, ground removed; radar
cropped to the box). Each frame's prediction is scored against its LiDAR with
``benchmarks.metrics.score_frame``; the table holds the mean over the frames.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msdnet.benchmarks.metrics import score_frame
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.pipeline import Pipeline
from msdnet.runtime.pointcloud import PointCloud


def _mean(values: list[float]) -> float:
    """Mean of the finite values (nan when none is finite)."""
    arr = np.asarray(values, dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    return float(arr.mean()) if arr.size else float("nan")


def load_frames(
    data: Path, dataset: str, count: int, pipe: Pipeline
) -> list[tuple[str, PointCloud, np.ndarray]]:
    """Up to ``count`` frames spread evenly over the dataset, preprocessed on the model's grid:
    (frame id, radar cloud with the model's columns, LiDAR (M, 3) float32 [x, y, z])."""
    from msdnet.runtime.datasets import open_dataset
    from msdnet.runtime.preprocess import preprocess_frame

    ds = open_dataset(dataset, data)
    ids = list(ds.frame_ids)
    if not ids:
        raise MsdnetError(data, "dataset has no frames")
    picks = sorted({int(i) for i in np.linspace(0, len(ids) - 1, min(count, len(ids)))})
    frames = []
    for i in tqdm(picks, desc="load frames", unit="frame", disable=None):
        frame = preprocess_frame(ds[i], pipe.artifact.grid)
        radar = frame.radar.select(pipe.columns)
        frames.append((ids[i], radar, np.asarray(frame.lidar.xyz, np.float32)))
    return frames


def quality_by_steps(
    pipe: Pipeline,
    frames: list[tuple[str, PointCloud, np.ndarray]],
    steps_list: tuple[int, ...],
    threshold: float,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Per step count: mean CD (m), MHD (m), JSD, MMD, F-score@0.2 m and decoded points over
    ``frames``, plus the median total latency (ms) of those calls."""
    lo, hi = pipe.artifact.grid.point_range[:3], pipe.artifact.grid.point_range[3:]
    xy_range = (lo[0], lo[1], hi[0], hi[1])
    rows = []
    for steps in tqdm(steps_list, desc="quality by T_m", unit="T_m", disable=None):
        scores, totals = [], []
        for _, radar, lidar in frames:
            res = pipe(radar, steps=steps, threshold=threshold, seed=seed)
            totals.append(res.timings["total"])
            scores.append(score_frame(res.points, lidar, xy_range))
        rows.append(
            {
                "steps": int(steps),
                "frames": len(frames),
                "cd": _mean([s.cd for s in scores]),
                "mhd": _mean([s.mhd for s in scores]),
                "jsd": _mean([s.jsd for s in scores]),
                "mmd": _mean([s.mmd for s in scores]),
                "fscore_0.2": _mean([s.fscore[0.2] for s in scores]),
                "points": float(np.mean([s.num_points for s in scores])),
                "ms": float(np.median(totals) * 1e3),
            }
        )
    return rows
