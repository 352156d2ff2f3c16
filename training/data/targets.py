"""Ground truth of the reconstruction head (MSDNet Eq. 5-7): occupancy and offsets per scale.

The LiDAR cloud is voxelized on the model grid with the runtime's voxelizer (no voxel cap).
Scale ``1/k`` (k = 4, 2, 1) has voxels ``k`` times larger per axis that start at the same corner,
so a coarse voxel is exactly the union of its ``k**3`` fine voxels; its grid is the encoder's
level-``log2 k`` grid, ``ceil(n / k)`` per axis (the last cell may reach past the range).

- occupancy: 1 where the coarse voxel holds at least one LiDAR point, else 0;
- offset: mean of its points - its centre, metres, channels ``[dx, dy, dz]`` (0 where empty).
  The mean is recombined exactly from the fine voxels' means and counts.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from msdnet.runtime.engine.rulebook import level_shapes
from msdnet.runtime.engine.voxelize import voxelize
from msdnet.runtime.spec.grid import GridConfig

SCALE_FACTORS = (4, 2, 1)  # voxel size multiple of scales 1/4, 1/2, 1, in head output order


def scale_shapes(grid: GridConfig) -> list[tuple[int, int, int]]:
    """Dense (D, H, W) per scale 1/4, 1/2, 1 (= encoder levels 2, 1, 0)."""
    levels = level_shapes(grid)
    return [levels[int(np.log2(k))] for k in SCALE_FACTORS]


def voxel_targets(points: np.ndarray, grid: GridConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """points: (N, >=3) float32 [x, y, z, ...] radar frame -> per scale 1/4, 1/2, 1:
    (occ (D, H, W) float32 in {0, 1}, off (3, D, H, W) float32 metres [dx, dy, dz])."""
    d, h, w = grid.shape_zyx
    vox = voxelize(np.asarray(points)[:, :3], grid, max_voxels=d * h * w)
    counts = vox.counts.astype(np.float64)  # (V,)
    sums = vox.features.astype(np.float64) * counts[:, None]  # (V, 3) [x, y, z] point sums
    lo = np.asarray(grid.point_range[:3], dtype=np.float64)
    size = np.asarray(grid.voxel_size, dtype=np.float64)
    out = []
    for k, (ds, hs, ws) in zip(SCALE_FACTORS, scale_shapes(grid), strict=True):
        c = vox.coords.astype(np.int64) // k  # (V, 3) [z, y, x] coarse indices
        lin = (c[:, 0] * hs + c[:, 1]) * ws + c[:, 2]  # (V,) coarse linear index
        cells, inv = np.unique(lin, return_inverse=True)  # (V_k,) occupied cells, (V,) -> cell
        cnt = np.bincount(inv, weights=counts)  # (V_k,) points per occupied cell
        mean = np.stack([np.bincount(inv, weights=sums[:, a]) for a in range(3)], axis=1) / cnt[:, None]
        zyx = np.stack(np.unravel_index(cells, (ds, hs, ws)), axis=1)  # (V_k, 3) [z, y, x]
        centres = lo + (zyx[:, ::-1] + 0.5) * size * k  # (V_k, 3) [x, y, z] metres
        occ = np.zeros(ds * hs * ws, np.float32)
        occ[cells] = 1.0
        off = np.zeros((3, ds * hs * ws), np.float32)  # [dx, dy, dz] per cell
        off[:, cells] = (mean - centres).T
        out.append((occ.reshape(ds, hs, ws), off.reshape(3, ds, hs, ws)))
    return out


def make_targets(clouds: Sequence[np.ndarray], grid: GridConfig) -> list[tuple[Tensor, Tensor]]:
    """clouds: list of B LiDAR (N_i, >=3) [x, y, z, ...] -> per scale 1/4, 1/2, 1:
    (occ (B, D, H, W) float32, off (B, 3, D, H, W) float32)."""
    per_cloud = [voxel_targets(c, grid) for c in clouds]
    out = []
    for s in range(len(SCALE_FACTORS)):
        occ = np.stack([t[s][0] for t in per_cloud])  # (B, D, H, W)
        off = np.stack([t[s][1] for t in per_cloud])  # (B, 3, D, H, W)
        out.append((torch.from_numpy(occ), torch.from_numpy(off)))
    return out
