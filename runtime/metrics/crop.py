"""The crop every metric scores in: the grid box and the radar's field of view."""

from __future__ import annotations

import numpy as np

from msdnet.runtime.io.datasets.preprocess import crop_mask
from msdnet.runtime.spec.grid import GridConfig


def crop_to_grid(points: np.ndarray, grid: GridConfig) -> np.ndarray:
    """points: (N, >=3) [x, y, z, ...] radar frame -> (M, 3) float32 inside the grid box and the
    radar's field of view: the same crop as the LiDAR reference gets."""
    xyz = np.asarray(points, dtype=np.float32)[:, :3]
    return np.ascontiguousarray(xyz[crop_mask(xyz, grid, fov=True)])


def xy_range(grid: GridConfig) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) of the grid: the BEV area of JSD / MMD."""
    r = grid.point_range
    return (r[0], r[1], r[3], r[4])
