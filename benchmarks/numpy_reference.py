"""Plain numpy references of the numba voxelizer, rulebooks and decoder.

Written the obvious way (``np.unique``, ``np.bincount``, ``np.searchsorted`` per kernel tap) so
they are easy to trust; the tests compare the numba kernels against them and
``msdnet-bench voxelize`` times the kernels against them. Same rules as the runtime modules
(``msdnet.runtime.engine.voxelize``, ``.rulebook``, ``.decode``), same float64 arithmetic.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from msdnet.runtime.engine.voxelize import Voxels
from msdnet.runtime.spec.grid import GridConfig


def voxelize_numpy(points: np.ndarray, grid: GridConfig, max_voxels: int) -> Voxels:
    """Reference of ``msdnet.runtime.engine.voxelize.voxelize``. points: (N, C) float32 [x, y, z, ...]."""
    pts = np.asarray(points, dtype=np.float32)
    c = pts.shape[1]
    lo = np.asarray(grid.point_range[:3], dtype=np.float64)
    hi = np.asarray(grid.point_range[3:], dtype=np.float64)
    size = np.asarray(grid.voxel_size, dtype=np.float64)
    nx, ny, nz = grid.shape_xyz
    xyz = pts[:, :3].astype(np.float64)  # (N, 3) [x, y, z]
    keep = np.isfinite(pts).all(axis=1)
    for j in range(3):  # per column: much faster than (xyz >= lo).all(axis=1) on (N, 3)
        keep &= (xyz[:, j] >= lo[j]) & (xyz[:, j] < hi[j])
    xyz, kept = xyz[keep], pts[keep]
    idx = np.floor((xyz - lo) * (1.0 / size)).astype(np.int64)  # (M, 3) [ix, iy, iz]
    idx = np.minimum(idx, np.array([nx - 1, ny - 1, nz - 1]))
    lin = (idx[:, 2] * ny + idx[:, 1]) * nx + idx[:, 0]
    keys, inverse, counts = np.unique(lin, return_inverse=True, return_counts=True)
    sums = np.stack(
        [np.bincount(inverse, weights=kept[:, j].astype(np.float64), minlength=keys.size) for j in range(c)],
        axis=1,
    ).reshape(keys.size, c)  # (V, C) float64
    dropped_cap = 0
    if keys.size > max_voxels:
        order = np.lexsort((keys, -counts))  # most points first, ties -> lower linear index
        chosen = np.sort(order[:max_voxels])
        dropped_cap = int(counts.sum() - counts[chosen].sum())
        keys, counts, sums = keys[chosen], counts[chosen], sums[chosen]
    coords = np.stack([keys // (nx * ny), (keys // nx) % ny, keys % nx], axis=1).astype(np.int32)
    feats = (sums * (1.0 / counts)[:, None]).astype(np.float32)
    return Voxels(coords.reshape(-1, 3), counts.astype(np.int32), feats,
                  int(pts.shape[0] - keep.sum()), dropped_cap)  # fmt: skip


def _keys(coords: np.ndarray, shape_zyx: Sequence[int]) -> np.ndarray:
    """(V, 4) [b, z, y, x] -> (V,) int64 keys in (b, linear index) order."""
    c = coords.astype(np.int64)
    d, h, w = shape_zyx
    return ((c[:, 0] * d + c[:, 1]) * h + c[:, 2]) * w + c[:, 3]


def rules_numpy(
    in_coords: np.ndarray,
    shape_zyx: Sequence[int],
    out_coords: np.ndarray,
    stride: int,
    padding: int,
) -> np.ndarray:
    """Reference rulebook: (M, 27) int32, rules[o, k] = row of in_coords at
    out_coords[o] * stride - padding + (kz, ky, kx) (same b) else V. Brute force per tap."""
    n_in = in_coords.shape[0]
    in_keys = _keys(in_coords, shape_zyx)
    rules = np.full((out_coords.shape[0], 27), n_in, np.int32)
    if n_in == 0:
        return rules
    shape = np.asarray(shape_zyx)
    for k in range(27):
        tap = np.array([k // 9, (k // 3) % 3, k % 3])  # (kz, ky, kx)
        pos = out_coords[:, 1:].astype(np.int64) * stride - padding + tap  # (M, 3) [z, y, x]
        inside = ((pos >= 0) & (pos < shape)).all(axis=1)
        query = np.concatenate([out_coords[:, :1].astype(np.int64), pos], axis=1)  # (M, 4)
        qk = _keys(np.where(inside[:, None], query, 0), shape_zyx)
        j = np.minimum(np.searchsorted(in_keys, qk), n_in - 1)
        hit = inside & (in_keys[j] == qk)
        rules[hit, k] = j[hit]
    return rules


def subm_rulebook_numpy(coords: np.ndarray, shape_zyx: Sequence[int]) -> np.ndarray:
    """Reference of ``subm_rulebook``: coords (V, 4) [b, z, y, x] sorted -> (V, 27) int32."""
    return rules_numpy(coords, shape_zyx, coords, 1, 1)


def down_rulebook_numpy(
    coords: np.ndarray, shape_zyx: Sequence[int], stride: int = 2, padding: int = 1
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """Reference of ``down_rulebook``: every (input, tap) pair proposes the output
    (i + padding - k) / stride where that is a whole index inside the output grid."""
    out_shape = tuple((int(n) + 2 * padding - 3) // stride + 1 for n in shape_zyx)
    c = coords.astype(np.int64)
    props = []  # per tap: (V_k, 4) [b, z', y', x'] proposed outputs
    for k in range(27):
        tap = np.array([k // 9, (k // 3) % 3, k % 3])
        t = c[:, 1:] + padding - tap  # (V, 3) [z, y, x]
        ok = ((t >= 0) & (t % stride == 0) & (t // stride < np.asarray(out_shape))).all(axis=1)
        props.append(np.concatenate([c[ok, :1], t[ok] // stride], axis=1))
    keys = np.unique(_keys(np.concatenate(props, axis=0), out_shape))  # sorted (b, linear)
    d, h, w = out_shape
    out = np.stack([keys // (d * h * w), keys // (h * w) % d, keys // w % h, keys % w], axis=1)
    out = out.astype(np.int32).reshape(-1, 4)
    return out, rules_numpy(coords, shape_zyx, out, stride, padding), out_shape  # type: ignore[return-value]


def decode_numpy(
    occupancy: np.ndarray, offsets: np.ndarray, grid: GridConfig, threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """Reference of ``decode_occupancy``: occupancy (D, H, W), offsets (3, D, H, W) [dx, dy, dz]
    -> points (M, 3) float32 [x, y, z], confidence (M,) float32, linear-index order."""
    hit = occupancy > np.float32(threshold)
    z, y, x = np.nonzero(hit)  # C order = linear-index order
    lo = np.asarray(grid.point_range[:3], dtype=np.float64)
    size = np.asarray(grid.voxel_size, dtype=np.float64)
    idx = np.stack([x, y, z], axis=1).astype(np.float64)  # (M, 3) [x, y, z] indices
    off = offsets[:, z, y, x].T.astype(np.float64)  # (M, 3) [dx, dy, dz]
    points = (lo + (idx + 0.5) * size + off).astype(np.float32)
    return points.reshape(-1, 3), occupancy[z, y, x].astype(np.float32)
