"""Quality beside latency (MSDNet Table III): the metrics of a model's output at each step count.

Frames come from a dataset folder (``vod``, ``astyx`` or ``sim`` layout; one split, or all),
preprocessed as for training (LiDAR cropped to the grid box and the radar's field of view, ground
removed; radar cropped to the box). Each prediction is cropped like the reference and scored with
``runtime.metrics.cloud.score_frame``, exactly as ``msdnet-bench quality`` does, so the figures compare
with its tables; the rows hold the mean over the frames (``quality.suite.summarize``). Step counts
run round-robin per frame (the order rotated per frame), so a burst of other load hits them all.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msdnet.benchmarks.quality.suite import pick_frames, summarize
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.metrics.cloud import FrameScores, score_frame
from msdnet.runtime.metrics.crop import crop_to_grid, xy_range


def load_frames(
    data: Path,
    dataset: str,
    count: int | None,
    pipe: Pipeline,
    split: str | None = None,
    frame_ids: list[str] | None = None,
) -> list[tuple[str, PointCloud, np.ndarray]]:
    """Up to ``count`` frames (None: all) of ``split`` (None: every frame; or exactly ``frame_ids``),
    spread evenly and in order, preprocessed on the model's grid: (frame id, radar cloud with the
    model's columns, LiDAR (M, 3) float32 [x, y, z])."""
    from msdnet.runtime.io.datasets import open_dataset
    from msdnet.runtime.io.datasets.preprocess import preprocess_frame

    ds = open_dataset(dataset, data, split)
    ids = pick_frames(list(ds.frame_ids) if frame_ids is None else frame_ids, count)
    if not ids:
        raise MsdnetError(data, f"dataset has no frames{f' in split {split!r}' if split else ''}")
    frames = []
    for fid in tqdm(ids, desc="load frames", unit="frame", disable=None):
        frame = preprocess_frame(ds.get(fid), pipe.artifact.grid)
        radar = frame.radar.select(pipe.columns)
        frames.append((fid, radar, crop_to_grid(frame.lidar.xyz, pipe.artifact.grid)))
    return frames


def quality_by_steps(
    pipe: Pipeline,
    frames: list[tuple[str, PointCloud, np.ndarray]],
    steps_list: tuple[int, ...],
    threshold: float | None,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Per step count: the mean of every metric over ``frames`` (``quality.suite.summarize``: cd,
    cd_squared, mhd, fscore@t, jsd, mmd, points, frames, empty_frames), ``fscore_0.2`` (its old
    name) and the median ms per frame of those calls: ``ms`` (total) and ``loop_ms`` (DDIM loop)."""
    grid = pipe.artifact.grid
    area = xy_range(grid)
    scores: dict[int, list[FrameScores]] = {s: [] for s in steps_list}
    totals: dict[int, list[float]] = {s: [] for s in steps_list}
    loops: dict[int, list[float]] = {s: [] for s in steps_list}
    if frames:
        pipe(frames[0][1], steps=steps_list[0], threshold=threshold, seed=seed)  # warm-up, untimed
    order = list(steps_list)
    bar = tqdm(total=len(frames) * len(order), desc="quality by T_m", unit="call", disable=None)
    for k, (_, radar, lidar) in enumerate(frames):
        for steps in order[k % len(order) :] + order[: k % len(order)]:
            res = pipe(radar, steps=steps, threshold=threshold, seed=seed)
            totals[steps].append(res.timings["total"])
            loops[steps].append(res.timings["denoise"])
            scores[steps].append(score_frame(crop_to_grid(res.points, grid), lidar, area))
            bar.update()
    bar.close()
    rows = []
    for steps in steps_list:
        row: dict[str, Any] = {"steps": int(steps), **summarize(scores[steps])}
        row["fscore_0.2"] = row["fscore@0.2"]
        row["ms"] = float(np.median(totals[steps]) * 1e3) if totals[steps] else float("nan")
        row["ms_p90"] = float(np.percentile(totals[steps], 90) * 1e3) if totals[steps] else float("nan")
        row["loop_ms"] = float(np.median(loops[steps]) * 1e3) if loops[steps] else float("nan")
        rows.append(row)
    return rows
