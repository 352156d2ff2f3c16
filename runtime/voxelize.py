"""Numba voxelizer: points -> occupied voxels with per-voxel mean features, in a fixed order.

Rules (the numpy reference in ``msdnet.benchmarks.numpy_reference`` follows them exactly):

1. A row is kept when every column is finite and ``lo <= p < hi`` on x, y and z (half-open,
   compared in float64 against the grid's ``point_range``). Dropped rows are counted in
   ``Voxels.dropped_out_of_range`` (non-finite rows included).
2. Voxel index per axis: ``floor((float64(p) - lo) / voxel_size)``, clipped to ``n - 1`` (a
   point a hair below ``hi`` may round up to ``n``). Linear index ``((z * H) + y) * W + x``.
3. Features: the mean of EVERY input column over the voxel's points, summed in float64 in input
   order, divided by the count, then cast to float32.
4. Order: voxels ascending by linear index. Cap: with more than ``max_voxels`` occupied, keep the
   ``max_voxels`` with the most points (ties -> lower linear index), still in linear order; the
   points of the dropped voxels are counted in ``Voxels.dropped_over_cap``.

The kernel is O(N): voxel keys are grouped with a stable LSD radix sort (11-bit digits, two
passes for the paper grid's 4.1M cells), so there is no dense grid and no comparison sort.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from msdnet.runtime.grid import GridConfig

RADIX_BITS = 11  # bits per LSD radix pass: 2048 buckets keep the histogram in L1


@dataclass(frozen=True, eq=False)
class Voxels:
    """Occupied voxels of one cloud, ascending by linear index ``((z * H) + y) * W + x``."""

    coords: np.ndarray  # (V, 3) int32 [z, y, x] voxel indices
    counts: np.ndarray  # (V,) int32 points per voxel (>= 1)
    features: np.ndarray  # (V, C) float32 per-voxel mean of every input column
    dropped_out_of_range: int  # rows outside point_range or with a non-finite value
    dropped_over_cap: int  # points in the voxels dropped by the max_voxels cap


@njit(cache=True)
def radix_sort_keys(keys: np.ndarray, max_key: int) -> tuple[np.ndarray, np.ndarray]:
    """Stable LSD radix sort of non-negative int64 keys.

    keys: (N,) int64 in ``0..max_key``. Returns ``(sorted_keys (N,) int64, perm (N,) int64)``
    with ``sorted_keys == keys[perm]``; equal keys keep their input order.
    """
    n = keys.size
    src_k = keys.copy()
    src_p = np.arange(n)
    if n < 2:
        return src_k, src_p
    bits = 0
    while (max_key >> bits) > 0:
        bits += 1
    dst_k = np.empty(n, np.int64)
    dst_p = np.empty(n, np.int64)
    shift = 0
    while shift < bits:
        nb = min(RADIX_BITS, bits - shift)
        mask = (1 << nb) - 1
        hist = np.zeros((1 << nb) + 1, np.int64)
        for i in range(n):
            hist[((src_k[i] >> shift) & mask) + 1] += 1
        for d in range(1 << nb):
            hist[d + 1] += hist[d]
        for i in range(n):
            d = (src_k[i] >> shift) & mask
            pos = hist[d]
            dst_k[pos] = src_k[i]
            dst_p[pos] = src_p[i]
            hist[d] = pos + 1
        src_k, dst_k = dst_k, src_k
        src_p, dst_p = dst_p, src_p
        shift += nb
    return src_k, src_p


@njit(cache=True)
def _voxelize_kernel(
    points: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    size: np.ndarray,
    shape_xyz: np.ndarray,
    max_voxels: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """points (N, C) float32 -> (coords (V,3) int32, counts (V,) int32, features (V,C) float32,
    dropped_out_of_range, dropped_over_cap). lo/hi/size: (3,) float64 [x, y, z];
    shape_xyz: (3,) int64 voxels along x, y, z."""
    n, c = points.shape
    nx, ny, nz = shape_xyz[0], shape_xyz[1], shape_xyz[2]
    keys = np.empty(n, np.int64)
    rows = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        ok = True
        for j in range(c):
            if not math.isfinite(points[i, j]):
                ok = False
                break
        if not ok:
            continue
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        if not (lo[0] <= x < hi[0] and lo[1] <= y < hi[1] and lo[2] <= z < hi[2]):
            continue
        ix = min(np.int64(math.floor((x - lo[0]) / size[0])), nx - 1)
        iy = min(np.int64(math.floor((y - lo[1]) / size[1])), ny - 1)
        iz = min(np.int64(math.floor((z - lo[2]) / size[2])), nz - 1)
        keys[m] = (iz * ny + iy) * nx + ix
        rows[m] = i
        m += 1
    dropped_range = n - m
    skeys, perm = radix_sort_keys(keys[:m], nx * ny * nz - 1)

    # Group the sorted keys: one voxel per run, sums in float64 in input order.
    n_vox = 0
    for t in range(m):
        if t == 0 or skeys[t] != skeys[t - 1]:
            n_vox += 1
    vkeys = np.empty(n_vox, np.int64)
    counts = np.zeros(n_vox, np.int32)
    sums = np.zeros((n_vox, c), np.float64)
    v = -1
    for t in range(m):
        if t == 0 or skeys[t] != skeys[t - 1]:
            v += 1
            vkeys[v] = skeys[t]
        counts[v] += 1
        r = rows[perm[t]]
        for j in range(c):
            sums[v, j] += points[r, j]

    # Cap: keep the max_voxels fullest voxels, ties -> lower linear index; O(V + max count).
    keep = np.ones(n_vox, np.bool_)
    dropped_cap = 0
    if n_vox > max_voxels:
        max_count = 0
        for v in range(n_vox):
            max_count = max(max_count, counts[v])
        hist = np.zeros(max_count + 2, np.int64)
        for v in range(n_vox):
            hist[counts[v]] += 1
        above = 0  # voxels with count > thr
        thr = max_count
        while above + hist[thr] < max_voxels:
            above += hist[thr]
            thr -= 1
        ties_left = max_voxels - above
        for v in range(n_vox):
            if counts[v] > thr:
                continue
            if counts[v] == thr and ties_left > 0:
                ties_left -= 1
                continue
            keep[v] = False
            dropped_cap += counts[v]
    n_keep = min(n_vox, max_voxels)

    coords = np.empty((n_keep, 3), np.int32)
    out_counts = np.empty(n_keep, np.int32)
    features = np.empty((n_keep, c), np.float32)
    k = 0
    for v in range(n_vox):
        if not keep[v]:
            continue
        key = vkeys[v]
        coords[k, 2] = key % nx
        coords[k, 1] = (key // nx) % ny
        coords[k, 0] = key // (nx * ny)
        out_counts[k] = counts[v]
        for j in range(c):
            features[k, j] = np.float32(sums[v, j] / counts[v])
        k += 1
    return coords, out_counts, features, dropped_range, dropped_cap


def grid_arrays(grid: GridConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The grid as kernel arguments: lo, hi, size (3,) float64 [x, y, z]; shape (3,) int64 [x, y, z]."""
    lo = np.asarray(grid.point_range[:3], dtype=np.float64)
    hi = np.asarray(grid.point_range[3:], dtype=np.float64)
    size = np.asarray(grid.voxel_size, dtype=np.float64)
    shape = np.asarray(grid.shape_xyz, dtype=np.int64)
    return lo, hi, size, shape


def voxelize(points: np.ndarray, grid: GridConfig, max_voxels: int) -> Voxels:
    """Voxelize one cloud (rules in the module docstring).

    points: (N, C) float32, C >= 3, columns [x, y, z, ...] in metres (other dtypes are cast).
    max_voxels: the cap on returned voxels, >= 1.
    Raises ValueError on a wrong shape or cap.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, C>=3) [x, y, z, ...], got shape {pts.shape}")
    if int(max_voxels) < 1:
        raise ValueError(f"max_voxels must be >= 1, got {max_voxels}")
    pts = np.ascontiguousarray(pts, dtype=np.float32)
    lo, hi, size, shape = grid_arrays(grid)
    coords, counts, feats, d_range, d_cap = _voxelize_kernel(
        pts, lo, hi, size, shape, np.int64(max_voxels)
    )
    return Voxels(coords, counts, feats, int(d_range), int(d_cap))


def warmup() -> None:
    """Compile (or load from numba's cache) the voxelizer, rulebook builder and decoder."""
    from msdnet.runtime.decode import warmup as warm_decode
    from msdnet.runtime.rulebook import warmup as warm_rulebook

    grid = GridConfig((0.0, 0.0, 0.0, 1.0, 1.0, 1.0), (0.5, 0.5, 0.5))
    pts = np.array([[0.1, 0.1, 0.1, 1.0], [0.6, 0.6, 0.6, 2.0], [0.2, 0.1, 0.1, 3.0]], np.float32)
    voxelize(pts, grid, max_voxels=1)
    warm_rulebook()
    warm_decode()
