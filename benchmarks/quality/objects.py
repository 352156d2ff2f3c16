"""Object-level quality: how well each method fills the labelled objects the LiDAR sees.

An object is **scored** when its box centre lies in the evaluation crop (grid box and field of
view, ``crop_mask``) and the reference (the preprocessed LiDAR: crop, ground removed) holds at
least ``MIN_LIDAR_POINTS`` points in the box grown by ``GROW`` metres on every face. For each
scored object and each method's cloud (cropped like the reference):

- **hit@5**: the object is hit when the cloud has at least ``HIT_POINTS`` points in the grown box;
  the share of objects hit;
- **object CD** (m): Chamfer distance (``chamfer_distance``: mean of both directed mean
  nearest-neighbour distances) between the cloud's and the LiDAR's points in the grown box, over
  the objects hit;
- **points per object**: the cloud's points in the grown box, beside the LiDAR's count.

Each is given over all objects, per class and per range band (``RANGE_BANDS``, horizontal
distance of the box centre from the radar; the last band runs to the crop's edge).

**Radar kept**: of the input radar points (cropped like the reference) within ``KEEP_RADIUS`` of
a LiDAR point, the share with a point of the method's cloud within ``KEEP_RADIUS``; pooled over
frames (kept / near summed first). The radar row keeps all of them by definition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from msdnet.runtime.io.datasets.astyx_boxes import Boxes
from msdnet.runtime.io.datasets.preprocess import crop_mask
from msdnet.runtime.metrics.cloud import chamfer_distance
from msdnet.runtime.spec.grid import GridConfig

GROW = 0.25  # metres added to every face of a box
MIN_LIDAR_POINTS = 10  # reference points in the grown box for an object to count as seen
HIT_POINTS = 5  # cloud points in the grown box for a hit
KEEP_RADIUS = 0.2  # metres: radar point "on a surface" / "kept"
RANGE_BANDS: tuple[tuple[str, float, float], ...] = (
    ("0–10 m", 0.0, 10.0),
    ("10–20 m", 10.0, 20.0),
    ("20–32 m", 20.0, math.inf),
)  # (label, from, to): horizontal range of the box centre, metres, [from, to)


@dataclass(frozen=True, eq=False)
class FrameObjects:
    """The scored objects of one frame and their reference points."""

    boxes: Boxes  # the K scored boxes (radar frame)
    lidar: tuple[np.ndarray, ...]  # K arrays (L_k, 3) float64: reference points in the grown box
    ranges: np.ndarray  # (K,) float64 horizontal range of each box centre, metres

    def __len__(self) -> int:
        return len(self.boxes)


def range_band(r: float) -> str:
    """The label of the ``RANGE_BANDS`` band holding range ``r`` metres."""
    for label, lo, hi in RANGE_BANDS:
        if lo <= r < hi:
            return label
    return RANGE_BANDS[-1][0]


def scored_objects(boxes: Boxes, ref: np.ndarray, grid: GridConfig) -> FrameObjects:
    """boxes: the frame's labels; ref: (N, >=3) the preprocessed LiDAR reference -> the objects
    that are scored (module docstring) with their reference points."""
    ref = np.asarray(ref, dtype=np.float64)[:, :3]
    keep, lidar = [], []
    in_crop = crop_mask(boxes.centers, grid, fov=True) if len(boxes) else np.zeros(0, bool)
    for k in range(len(boxes)):
        if not in_crop[k]:
            continue
        pts = ref[boxes.contains(ref, k, GROW)]
        if len(pts) >= MIN_LIDAR_POINTS:
            keep.append(k)
            lidar.append(pts)
    mask = np.zeros(len(boxes), bool)
    mask[keep] = True
    chosen = boxes.subset(mask)
    return FrameObjects(chosen, tuple(lidar), np.hypot(chosen.centers[:, 0], chosen.centers[:, 1]))


def score_objects(pred: np.ndarray, objects: FrameObjects) -> np.ndarray:
    """pred: (M, >=3) a method's cloud -> (K, 3) float64 per scored object: [cloud points in the
    grown box, object CD (m; nan when not hit), reference points in the grown box]."""
    pred = np.asarray(pred, dtype=np.float64)[:, :3]
    out = np.full((len(objects), 3), np.nan)
    for k in range(len(objects)):
        inside = pred[objects.boxes.contains(pred, k, GROW)]
        out[k, 0] = len(inside)
        out[k, 2] = len(objects.lidar[k])
        if len(inside) >= HIT_POINTS:
            out[k, 1] = chamfer_distance(inside, objects.lidar[k])
    return out


def near_radar(radar: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(R, 3) float64: the radar points (R0, >=3) within ``KEEP_RADIUS`` of a reference point."""
    radar = np.asarray(radar, dtype=np.float64)[:, :3]
    if len(radar) == 0 or len(ref) == 0:
        return np.zeros((0, 3))
    d, _ = cKDTree(np.asarray(ref, dtype=np.float64)[:, :3]).query(radar, k=1)
    return radar[d <= KEEP_RADIUS]


def radar_kept(near: np.ndarray, pred: np.ndarray) -> int:
    """near: (R, 3) radar points on a surface (``near_radar``); pred: (M, >=3) a cloud -> how many
    of them have a cloud point within ``KEEP_RADIUS``."""
    if len(near) == 0 or len(pred) == 0:
        return 0
    d, _ = cKDTree(np.asarray(pred, dtype=np.float64)[:, :3]).query(near, k=1)
    return int((d <= KEEP_RADIUS).sum())


@dataclass
class ObjectTally:
    """One method's object rows and radar-kept counts over the frames of a run."""

    rows: list[tuple[str, str, str, float, float, float]] = field(default_factory=list)
    # (frame, class, range band, cloud points, object CD or nan, reference points)
    kept: int = 0  # radar points on a surface that the cloud keeps
    near: int = 0  # radar points on a surface

    def add(self, frame_id: str, objects: FrameObjects, pred: np.ndarray, near: np.ndarray) -> None:
        """Score ``pred`` on one frame's objects and surface radar points."""
        scores = score_objects(pred, objects)
        for k in range(len(objects)):
            band = range_band(float(objects.ranges[k]))
            self.rows.append((frame_id, objects.boxes.classes[k], band, *map(float, scores[k])))
        self.kept += radar_kept(near, pred)
        self.near += len(near)


def group_summary(rows: list[tuple[str, str, str, float, float, float]]) -> dict[str, float]:
    """Rows of one group -> {objects, hit@5, object_cd, points, lidar_points} (means; nan when
    there is no object / no hit)."""
    if not rows:
        return {"objects": 0, "hit@5": math.nan, "object_cd": math.nan, "points": math.nan,
                "lidar_points": math.nan}  # fmt: skip
    arr = np.asarray([r[3:] for r in rows], dtype=np.float64)  # (K, 3) points, CD, reference points
    hit = arr[:, 0] >= HIT_POINTS
    return {
        "objects": int(len(rows)),
        "hit@5": float(hit.mean()),
        "object_cd": float(arr[hit, 1].mean()) if hit.any() else math.nan,
        "points": float(arr[:, 0].mean()),
        "lidar_points": float(arr[:, 2].mean()),
    }


def summarize_objects(tally: ObjectTally) -> dict[str, Any]:
    """{overall, by_class, by_range, radar_kept: {share, kept, near}} of one method."""
    classes = sorted({r[1] for r in tally.rows}, key=lambda c: (-sum(r[1] == c for r in tally.rows), c))
    return {
        "overall": group_summary(tally.rows),
        "by_class": {c: group_summary([r for r in tally.rows if r[1] == c]) for c in classes},
        "by_range": {b: group_summary([r for r in tally.rows if r[2] == b]) for b, _, _ in RANGE_BANDS},
        "radar_kept": {
            "share": tally.kept / tally.near if tally.near else math.nan,
            "kept": tally.kept,
            "near": tally.near,
        },
    }


def objects_definition() -> dict[str, Any]:
    """The rules, for results.json."""
    return {
        "grow_m": GROW,
        "min_lidar_points": MIN_LIDAR_POINTS,
        "hit_points": HIT_POINTS,
        "keep_radius_m": KEEP_RADIUS,
        "range_bands_m": [[lo, hi if math.isfinite(hi) else None] for _, lo, hi in RANGE_BANDS],
        "what": "objects with the box centre in the crop and >= min_lidar_points reference points "
        "in the grown box; hit@5 share of objects with >= hit_points cloud points in the grown box; "
        "object CD over the objects hit; radar kept: share of radar points within keep_radius of "
        "the LiDAR that have a cloud point within keep_radius",
    }
