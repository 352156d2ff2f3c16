"""One preprocessing path for every dataset (as in R2LDM and MSDNet).

``preprocess_frame``: the LiDAR (already in the radar frame) is cropped to the grid box and
the radar's horizontal field of view ``|atan2(y, x)| <= grid.fov_deg``, then its ground is
removed; the radar is cropped to the grid box only (radar needs no ground removal).

Ground removal runs on the LiDAR points in the LiDAR's OWN frame (moved back with
``frame.radar_to_lidar``), where the ground lies about one sensor height below the origin:

1. A robust plane fit (RANSAC over the lowest points, normals within ``max_tilt_deg`` of
   vertical, then a least-squares refit on the inliers) gives the sensor height per frame
   (``GroundConfig.sensor_height`` overrides it) — Patchwork++'s defaults are KITTI's 1.723 m.
2. Patchwork++ (``pypatchworkpp``) with that height classifies the points, with bin sizes
   per LiDAR rig (``GROUND_PRESETS[frame.lidar_rig]``). Reflected-noise removal is off
   (intensity scales differ between rigs). It comes with the ``metrics`` extra, imported on
   first use.
3. Fallback, documented and tested: if Patchwork++ raises, returns an inconsistent split or
   finds no ground at all, the plane from step 1 decides (``|distance| < plane_threshold``).
"""

from __future__ import annotations

import contextlib
import os
import sys
from dataclasses import dataclass, replace

import numpy as np

from msdnet.runtime.errors import import_extra
from msdnet.runtime.io.datasets.frame import Frame
from msdnet.runtime.spec.grid import GridConfig

KITTI_SENSOR_HEIGHT = 1.723  # m, Patchwork++'s default; used only when nothing better is known


@dataclass(frozen=True)
class GroundConfig:
    """Ground removal settings (per rig where it matters)."""

    method: str = "patchwork"  # "patchwork" (plane fallback on failure) or "plane"
    sensor_height: float | None = None  # LiDAR height above ground, m; None: from the plane fit
    th_dist: float = 0.125  # Patchwork++ distance threshold to its local planes, m
    min_range: float = 2.7  # Patchwork++ innermost range, m (KITTI default)
    max_range: float = 80.0  # Patchwork++ outermost range, m (KITTI default)
    rings_per_zone: tuple[int, ...] = (2, 4, 4, 4)  # Patchwork++ radial bins per zone (KITTI)
    sectors_per_zone: tuple[int, ...] = (16, 32, 54, 32)  # Patchwork++ azimuth bins per zone
    plane_threshold: float = 0.2  # fallback: |distance to the plane| below this is ground, m
    plane_low_quantile: float = 0.3  # RANSAC draws from the lowest 30 % of points
    plane_iterations: int = 100  # RANSAC plane hypotheses
    plane_sample: int = 2000  # low points the hypotheses are scored on (a random subset)
    max_tilt_deg: float = 15.0  # planes tilted more than this from horizontal are rejected
    seed: int = 0  # RANSAC sampling seed (deterministic results)


# per LiDAR rig (``Frame.lidar_rig``). A 16-beam sweep leaves one ring per Patchwork++ bin at
# KITTI's bin sizes, a line no plane can be fitted to, so ground rings beyond ~12 m stayed;
# coarser bins (measured on Astyx frames 0-400: points within 0.1 m of the ground plane left
# after removal fell from 78-211 to 9-83 per frame) fix that. Dense 64-beam sweeps keep the
# KITTI bins, which follow raised pavements and slopes better (VoD frame 00549).
GROUND_PRESETS: dict[str, GroundConfig] = {
    "hdl64": GroundConfig(),
    "vlp16": GroundConfig(rings_per_zone=(1, 1, 1, 1), sectors_per_zone=(8, 16, 27, 16)),
}


@dataclass(frozen=True)
class GroundResult:
    """Which points are ground, and how that was decided."""

    mask: np.ndarray  # (N,) bool, True for ground
    method: str  # "patchwork", "plane" (fallback or chosen) or "none" (too few points)
    sensor_height: float  # m, height used (from the config, the plane fit or KITTI's default)


def crop_mask(xyz: np.ndarray, grid: GridConfig, fov: bool = True) -> np.ndarray:
    """xyz: (N, 3) [x, y, z] radar frame -> (N,) bool: inside ``lo <= p < hi`` (and the FOV)."""
    p = np.asarray(xyz)
    mask = np.ones(len(p), dtype=bool)
    for i in range(3):
        mask &= (p[:, i] >= grid.point_range[i]) & (p[:, i] < grid.point_range[i + 3])
    if fov:
        idx = np.flatnonzero(mask)  # azimuth only for points inside the box
        azimuth = np.degrees(np.arctan2(p[idx, 1].astype(np.float64), p[idx, 0].astype(np.float64)))
        mask[idx[np.abs(azimuth) > grid.fov_deg]] = False
    return mask


def fit_ground_plane(xyz: np.ndarray, cfg: GroundConfig) -> tuple[np.ndarray, float] | None:
    """RANSAC plane on the lowest points. xyz: (N, 3) sensor frame.

    Returns ``(n, d)`` with unit normal ``n`` (n_z > 0) and ``n . p + d = 0`` on the plane, so
    ``d`` is the sensor's height above it; None when no acceptable plane exists.
    """
    p = np.asarray(xyz, dtype=np.float64)
    if len(p) < 10:
        return None
    low = p[p[:, 2] <= np.quantile(p[:, 2], cfg.plane_low_quantile)]
    if len(low) < 3:
        return None
    rng = np.random.default_rng(cfg.seed)
    if len(low) > cfg.plane_sample:
        low = low[rng.choice(len(low), cfg.plane_sample, replace=False)]
    samples = low[rng.integers(0, len(low), size=(cfg.plane_iterations, 3))]  # (I, 3 pts, 3)
    normals = np.cross(samples[:, 1] - samples[:, 0], samples[:, 2] - samples[:, 0])  # (I, 3)
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-9
    normals = normals[ok] / norm[ok, None]
    normals *= np.sign(normals[:, 2:3]) + (normals[:, 2:3] == 0)  # n_z >= 0
    origins = samples[ok, 0]
    level = normals[:, 2] >= np.cos(np.radians(cfg.max_tilt_deg))
    if not level.any():
        return None
    normals, origins = normals[level], origins[level]
    d = -np.einsum("ij,ij->i", normals, origins)  # (I,)
    inliers = np.abs(low @ normals.T + d) < cfg.plane_threshold  # (M, I)
    best = int(np.argmax(inliers.sum(axis=0)))
    n, off = normals[best], float(d[best])
    for _ in range(2):  # least-squares refit on the inliers of all points
        sel = p[np.abs(_plane_distance(p, n, off)) < cfg.plane_threshold]
        if len(sel) < 3:
            break
        centre = sel.mean(axis=0)
        n_new = np.linalg.svd(sel - centre, full_matrices=False)[2][-1]
        n_new = n_new if n_new[2] >= 0 else -n_new
        if n_new[2] < np.cos(np.radians(cfg.max_tilt_deg)):
            break
        n, off = n_new, float(-n_new @ centre)
    return n, off


def _plane_distance(p: np.ndarray, n: np.ndarray, off: float) -> np.ndarray:
    """p: (N, 3) -> (N,) signed distance ``n . p + off`` (per column: faster than ``p @ n``)."""
    return p[:, 0] * n[0] + p[:, 1] * n[1] + p[:, 2] * n[2] + off


@contextlib.contextmanager
def _quiet_stdout():
    """Silence C++ prints to fd 1 (Patchwork++ announces its initialisation there)."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:
        yield
        return
    with open(os.devnull, "wb") as null:
        os.dup2(null.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


def _patchwork(xyz: np.ndarray, height: float, cfg: GroundConfig) -> np.ndarray | None:
    """(N,) bool ground mask from Patchwork++, None when it fails (a missing ``metrics`` extra is
    an error, not a failure: the fallback is for a binding that runs and fails)."""
    pypatchworkpp = import_extra("pypatchworkpp", "ground removal")
    params = pypatchworkpp.Parameters()
    params.verbose = False
    params.sensor_height = float(height)
    params.th_dist = cfg.th_dist
    params.min_range = cfg.min_range
    params.max_range = cfg.max_range
    params.num_rings_each_zone = list(cfg.rings_per_zone)
    params.num_sectors_each_zone = list(cfg.sectors_per_zone)
    params.enable_RNR = False
    params.RNR_intensity_thr = 0.0
    params.intensity_thr = 0.0  # unused with RNR off; left uninitialised by the binding
    cloud = np.zeros((len(xyz), 4), dtype=np.float64)  # (N, 4) [x, y, z, intensity = 0]
    cloud[:, :3] = xyz
    try:
        with _quiet_stdout():
            pw = pypatchworkpp.patchworkpp(params)
            pw.estimateGround(cloud)
            ground = np.asarray(pw.getGroundIndices(), dtype=np.int64)
            nonground = np.asarray(pw.getNongroundIndices(), dtype=np.int64)
    except Exception:  # any failure of the binding: use the documented fallback
        return None
    if len(ground) == 0 or len(ground) + len(nonground) != len(xyz):
        return None
    if ground.min() < 0 or ground.max() >= len(xyz):
        return None
    mask = np.zeros(len(xyz), dtype=bool)
    mask[ground] = True
    return mask


def ground_mask(xyz_sensor: np.ndarray, cfg: GroundConfig | None = None) -> GroundResult:
    """Classify ground. xyz_sensor: (N, 3) [x, y, z] in the LiDAR's own frame."""
    cfg = cfg or GroundConfig()
    if cfg.method not in ("patchwork", "plane"):
        raise ValueError(f"unknown ground method {cfg.method!r} (patchwork or plane)")
    p = np.asarray(xyz_sensor, dtype=np.float64)
    plane = fit_ground_plane(p, cfg)
    height = cfg.sensor_height
    if height is None:
        height = plane[1] if plane is not None else KITTI_SENSOR_HEIGHT
    if cfg.method == "patchwork" and len(p) >= 10:
        mask = _patchwork(p, height, cfg)
        if mask is not None:
            return GroundResult(mask, "patchwork", float(height))
    if plane is None:
        return GroundResult(np.zeros(len(p), dtype=bool), "none", float(height))
    mask = np.abs(_plane_distance(p, *plane)) < cfg.plane_threshold
    return GroundResult(mask, "plane", float(height))


def preprocess_frame(
    frame: Frame,
    grid: GridConfig,
    remove_ground: bool = True,
    ground: GroundConfig | None = None,
) -> Frame:
    """Crop LiDAR to grid box + FOV and remove its ground; crop radar to the grid box.

    ``ground`` defaults to ``GROUND_PRESETS[frame.lidar_rig]``.
    """
    radar = frame.radar.subset(crop_mask(frame.radar.xyz, grid, fov=False))
    lidar = frame.lidar.subset(crop_mask(frame.lidar.xyz, grid, fov=True))
    cropped = replace(frame, radar=radar, lidar=lidar)
    if not remove_ground:
        return cropped
    return replace(cropped, lidar=lidar.subset(~lidar_ground(cropped, ground).mask))


def lidar_ground(frame: Frame, ground: GroundConfig | None = None) -> GroundResult:
    """Ground of ``frame.lidar`` (radar frame), classified in the LiDAR's own frame.

    ``ground`` defaults to the preset of ``frame.lidar_rig`` (KITTI settings if unknown).
    """
    cfg = ground or GROUND_PRESETS.get(frame.lidar_rig, GroundConfig())
    return ground_mask(frame.lidar_in_own_frame(), cfg)
