"""Occupancy decoder (numba): dense occupancy + offsets -> points with confidence.

Every voxel with ``occupancy > threshold`` (compared in float32) becomes one point at its voxel
centre plus its predicted offset, in linear-index order ``((z * H) + y) * W + x`` (deterministic).
Centre of voxel ``[z, y, x]`` per axis: ``lo + (index + 0.5) * voxel_size``; the centre and the
offset are added in float64, then cast to float32. Confidence is the occupancy value.

One branch-free pass over the dense grid (4.1M voxels on the paper grid) collects the linear
indices of the hits; a second pass over the hits only writes the points.

``decode_packed`` reads the head's packed layout (``onnx_spec.RECON_HEAD``: axis 0 the child
``(dz * 2 + dy) * 2 + dx`` of half-scale voxel ``[z2, y2, x2]``) and gives exactly the points of
``decode_occupancy`` on the dense grid, in the same order; ``unpack_children`` is the plain
numpy conversion, for comparisons outside the hot path.

``radar_confidence_packed`` / ``radar_confidence_sparse``: the confidence of each input radar point
from the head's own output, for keeping true radar returns as they are: the largest full-scale
occupancy over the 3 x 3 x 3 voxels around the point's voxel (the voxelizer's index rule, clamped
into the grid; neighbours outside the grid skipped). The dense head gives the full scale
everywhere; the coarse-to-fine head only under the half-scale voxels it decoded, and a voxel it
did not decode counts as occupancy 0.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from msdnet.runtime.engine.voxelize import grid_arrays
from msdnet.runtime.spec.grid import GridConfig
from msdnet.runtime.spec.range_threshold import RangeThresholds


@njit(cache=True, inline="always")
def _put_point(points: np.ndarray, t: int, lo: np.ndarray, size: np.ndarray, x: int, y: int, z: int,
               dx: np.float32, dy: np.float32, dz: np.float32) -> None:  # fmt: skip
    """points[t] = centre of voxel [z, y, x] plus the offset [dx, dy, dz]: the sum in float64, the
    store in float32 (the rule both decoders share)."""
    points[t, 0] = np.float32(lo[0] + (x + 0.5) * size[0] + np.float64(dx))
    points[t, 1] = np.float32(lo[1] + (y + 0.5) * size[1] + np.float64(dy))
    points[t, 2] = np.float32(lo[2] + (z + 0.5) * size[2] + np.float64(dz))


@njit(cache=True, inline="always")
def _passes(
    occ: np.float32, px: np.float32, py: np.float32, edges2: np.ndarray, thresholds: np.ndarray
) -> bool:
    """occ > the threshold of the band of horizontal range of the point [px, py] (float32, as
    stored): band = the number of ``edges2`` (squared edges, float64) <= px^2 + py^2 in float64
    (``RangeThresholds.per_point``'s rule)."""
    r2 = np.float64(px) * np.float64(px) + np.float64(py) * np.float64(py)
    b = 0
    while b < edges2.shape[0] and edges2[b] <= r2:
        b += 1
    return occ > thresholds[b]


@njit(cache=True)
def _decode_kernel(
    occupancy: np.ndarray, offsets: np.ndarray, lo: np.ndarray, size: np.ndarray, threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """occupancy (D, H, W) float32, offsets (3, D, H, W) float32 [dx, dy, dz], lo/size (3,)
    float64 [x, y, z], threshold float32 -> points (M, 3) float32 [x, y, z], confidence (M,)."""
    d, h, w = occupancy.shape
    n = d * h * w
    occ = occupancy.reshape(n)  # (D*H*W,) in linear-index order
    off = offsets.reshape(3, n)  # (3, D*H*W) [dx, dy, dz]
    # Branch-free: the slot is written every time and kept only on a hit. Pages of the buffer past
    # the last hit are never touched, so a sparse occupancy costs little memory.
    hits = np.empty(n, np.int32)
    m = 0
    for i in range(n):
        hits[m] = i
        m += occ[i] > threshold
    points = np.empty((m, 3), np.float32)
    confidence = np.empty(m, np.float32)
    for t in range(m):
        i = hits[t]
        x = i % w
        y = (i // w) % h
        z = i // (w * h)
        _put_point(points, t, lo, size, x, y, z, off[0, i], off[1, i], off[2, i])
        confidence[t] = occ[i]
    return points, confidence


def decode_occupancy(
    occupancy: np.ndarray, offsets: np.ndarray, grid: GridConfig, threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """Threshold the occupancy and place one point per kept voxel (rules in the module docstring).

    occupancy: (D, H, W) float32 in [0, 1]; offsets: (3, D, H, W) float32 [dx, dy, dz] metres;
    (D, H, W) must equal ``grid.shape_zyx``. Returns points (M, 3) float32 [x, y, z] and
    confidence (M,) float32. Raises ValueError on mismatched shapes.
    """
    occ = np.ascontiguousarray(occupancy, dtype=np.float32)
    if occ.size >= 2**31:
        raise ValueError(f"occupancy of {occ.size} voxels exceeds the int32 index")
    off = np.ascontiguousarray(offsets, dtype=np.float32)
    if occ.shape != tuple(grid.shape_zyx):
        raise ValueError(f"occupancy must be {grid.shape_zyx} (D, H, W), got {occ.shape}")
    if off.shape != (3, *occ.shape):
        raise ValueError(f"offsets must be (3, *{occ.shape}) [dx, dy, dz], got {off.shape}")
    lo, _, size, _ = grid_arrays(grid)
    return _decode_kernel(occ, off, lo, size, np.float32(threshold))


@njit(cache=True)
def _decode_packed_kernel(
    occupancy: np.ndarray,
    offsets: np.ndarray,
    shape_zyx: np.ndarray,
    lo: np.ndarray,
    size: np.ndarray,
    edges2: np.ndarray,
    thresholds: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """occupancy (8, D2, H2, W2), offsets (8, 3, D2, H2, W2) packed; shape_zyx (3,) int64 the
    dense (D, H, W); edges2 (B - 1,) float64 squared range edges, thresholds (B,) float32 (no edge:
    one threshold) -> points (M, 3) float32, confidence (M,) in dense linear-index order."""
    d, h, w = shape_zyx[0], shape_zyx[1], shape_zyx[2]
    hits = np.empty(d * h * w, np.int32)
    m = 0
    lowest = thresholds.min()
    for z in range(d):
        for y in range(h):
            row = ((z & 1) * 2 + (y & 1)) * 2
            for x in range(w):
                c = row + (x & 1)
                occ = occupancy[c, z >> 1, y >> 1, x >> 1]
                hits[m] = (z * h + y) * w + x
                if edges2.shape[0] == 0:
                    m += occ > lowest  # branch-free
                elif occ > lowest:
                    px = np.float32(
                        lo[0] + (x + 0.5) * size[0] + np.float64(offsets[c, 0, z >> 1, y >> 1, x >> 1])
                    )
                    py = np.float32(
                        lo[1] + (y + 0.5) * size[1] + np.float64(offsets[c, 1, z >> 1, y >> 1, x >> 1])
                    )
                    m += _passes(occ, px, py, edges2, thresholds)
    points = np.empty((m, 3), np.float32)
    confidence = np.empty(m, np.float32)
    for t in range(m):
        i = hits[t]
        x = i % w
        y = (i // w) % h
        z = i // (w * h)
        child = ((z & 1) * 2 + (y & 1)) * 2 + (x & 1)
        z2, y2, x2 = z >> 1, y >> 1, x >> 1
        cell = offsets[child, :, z2, y2, x2]  # (3,) [dx, dy, dz]
        _put_point(points, t, lo, size, x, y, z, cell[0], cell[1], cell[2])
        confidence[t] = occupancy[child, z2, y2, x2]
    return points, confidence


def packed_shape(grid: GridConfig) -> tuple[int, int, int]:
    """(D2, H2, W2): half-scale voxels covering the dense grid, ``ceil(n / 2)`` per axis."""
    return tuple((n + 1) // 2 for n in grid.shape_zyx)  # type: ignore[return-value]


def _band_arrays(threshold: float, bands: RangeThresholds | None) -> tuple[np.ndarray, np.ndarray]:
    """(squared edges (B - 1,) float64, thresholds (B,) float32) for the kernels."""
    if bands is None:
        return np.empty(0, np.float64), np.asarray([threshold], np.float32)
    return bands.squared_edges(), np.asarray(bands.thresholds, np.float32)


def decode_packed(
    occupancy: np.ndarray,
    offsets: np.ndarray,
    grid: GridConfig,
    threshold: float,
    bands: RangeThresholds | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``decode_occupancy`` on the packed head output, without unpacking it. With ``bands`` each
    voxel's threshold is that of its point's band of range (``spec.range_threshold``; the same
    points as decoding at the lowest and keeping ``bands.keep``'s), ``threshold`` unused.

    occupancy: (8, D2, H2, W2) float32; offsets: (8, 3, D2, H2, W2) float32 [dx, dy, dz] metres;
    ``(D2, H2, W2) == packed_shape(grid)``. Same points and order as ``decode_occupancy`` on
    ``unpack_children`` of the inputs. Raises ValueError on mismatched shapes.
    """
    occ = np.ascontiguousarray(occupancy, dtype=np.float32)
    off = np.ascontiguousarray(offsets, dtype=np.float32)
    half = packed_shape(grid)
    if occ.shape != (8, *half):
        raise ValueError(f"packed occupancy must be (8, *{half}), got {occ.shape}")
    if off.shape != (8, 3, *half):
        raise ValueError(f"packed offsets must be (8, 3, *{half}), got {off.shape}")
    if 8 * occ[0].size >= 2**31:
        raise ValueError(f"occupancy of {8 * occ[0].size} voxels exceeds the int32 index")
    lo, _, size, _ = grid_arrays(grid)
    shape = np.asarray(grid.shape_zyx, dtype=np.int64)
    return _decode_packed_kernel(occ, off, shape, lo, size, *_band_arrays(threshold, bands))


@njit(cache=True)
def _decode_sparse_kernel(
    occupancy: np.ndarray,
    offsets: np.ndarray,
    voxels: np.ndarray,
    shape_zyx: np.ndarray,
    lo: np.ndarray,
    size: np.ndarray,
    edges2: np.ndarray,
    thresholds: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """occupancy (N, 8), offsets (N, 8, 3), voxels (N,) int64 linear half-scale indices;
    shape_zyx (3,) int64 the dense (D, H, W); edges2, thresholds as ``_decode_packed_kernel`` ->
    points (M, 3), confidence (M,) in dense linear-index order (children outside the dense grid
    are skipped, as the dense crop does)."""
    lowest = thresholds.min()
    d, h, w = shape_zyx[0], shape_zyx[1], shape_zyx[2]
    h2, w2 = (h + 1) // 2, (w + 1) // 2
    n = voxels.shape[0]
    keys = np.empty(8 * n, np.int64)  # dense linear index of each hit
    slots = np.empty(8 * n, np.int64)  # row * 8 + child of each hit
    m = 0
    for r in range(n):
        v = voxels[r]
        x2 = v % w2
        y2 = (v // w2) % h2
        z2 = v // (w2 * h2)
        for child in range(8):
            z = 2 * z2 + (child >> 2)
            y = 2 * y2 + ((child >> 1) & 1)
            x = 2 * x2 + (child & 1)
            occ = occupancy[r, child]
            if z < d and y < h and x < w and occ > lowest:
                if edges2.shape[0] > 0:
                    px = np.float32(lo[0] + (x + 0.5) * size[0] + np.float64(offsets[r, child, 0]))
                    py = np.float32(lo[1] + (y + 0.5) * size[1] + np.float64(offsets[r, child, 1]))
                    if not _passes(occ, px, py, edges2, thresholds):
                        continue
                keys[m] = (z * h + y) * w + x
                slots[m] = r * 8 + child
                m += 1
    order = np.argsort(keys[:m])
    points = np.empty((m, 3), np.float32)
    confidence = np.empty(m, np.float32)
    for t in range(m):
        i = keys[order[t]]
        r = slots[order[t]] // 8
        child = slots[order[t]] % 8
        x = i % w
        y = (i // w) % h
        z = i // (w * h)
        _put_point(
            points, t, lo, size, x, y, z, offsets[r, child, 0], offsets[r, child, 1], offsets[r, child, 2]
        )
        confidence[t] = occupancy[r, child]
    return points, confidence


def decode_sparse(
    occupancy: np.ndarray,
    offsets: np.ndarray,
    voxels: np.ndarray,
    grid: GridConfig,
    threshold: float,
    bands: RangeThresholds | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``decode_occupancy`` on the coarse-to-fine head's output (``onnx_spec.RECON_HEAD_SPARSE``);
    ``bands`` as ``decode_packed``'s.

    occupancy: (N, 8) float32; offsets: (N, 8, 3) float32 [dx, dy, dz] metres; voxels: (N,)
    int64 linear half-scale indices ``(z2 * H2 + y2) * W2 + x2`` with ``(D2, H2, W2) ==
    packed_shape(grid)``. Same points and order as ``decode_packed`` on the dense head's output
    when every half-scale voxel with a child above the threshold is among ``voxels``. Raises
    ValueError on mismatched shapes or an index outside the half-scale grid.
    """
    occ = np.ascontiguousarray(occupancy, dtype=np.float32)
    off = np.ascontiguousarray(offsets, dtype=np.float32)
    vox = np.ascontiguousarray(voxels, dtype=np.int64)
    n = vox.shape[0] if vox.ndim == 1 else -1
    if occ.shape != (n, 8) or off.shape != (n, 8, 3):
        raise ValueError(
            f"sparse head output must be (N, 8), (N, 8, 3), (N,); got {occ.shape}, {off.shape}, {vox.shape}"
        )
    half = packed_shape(grid)
    if n and (vox.min() < 0 or vox.max() >= half[0] * half[1] * half[2]):
        raise ValueError(f"voxel index outside the half-scale grid {half}")
    lo, _, size, _ = grid_arrays(grid)
    shape = np.asarray(grid.shape_zyx, dtype=np.int64)
    return _decode_sparse_kernel(occ, off, vox, shape, lo, size, *_band_arrays(threshold, bands))


def unpack_children(packed: np.ndarray, shape_zyx: tuple[int, int, int]) -> np.ndarray:
    """(8, ..., D2, H2, W2) packed -> (..., D, H, W) dense (numpy transpose, then crop)."""
    lead = packed.shape[1:-3]
    d2, h2, w2 = packed.shape[-3:]
    x = packed.reshape(2, 2, 2, *lead, d2, h2, w2)  # (dz, dy, dx, ..., D2, H2, W2)
    k = len(lead)
    axes = (*range(3, 3 + k), 3 + k, 0, 4 + k, 1, 5 + k, 2)  # (..., D2, dz, H2, dy, W2, dx)
    dense = x.transpose(axes).reshape(*lead, 2 * d2, 2 * h2, 2 * w2)
    d, h, w = shape_zyx
    return np.ascontiguousarray(dense[..., :d, :h, :w])


def warmup() -> None:
    """Compile (or load from numba's cache) the decoder with a tiny input."""
    grid = GridConfig((0.0, 0.0, 0.0, 1.0, 1.0, 1.0), (0.5, 0.5, 0.5))
    occ = np.zeros(grid.shape_zyx, np.float32)
    occ[0, 1, 0] = 0.9
    decode_occupancy(occ, np.zeros((3, *grid.shape_zyx), np.float32), grid, 0.5)
    half = packed_shape(grid)
    decode_packed(np.zeros((8, *half), np.float32), np.zeros((8, 3, *half), np.float32), grid, 0.5)
    decode_sparse(
        np.full((1, 8), 0.9, np.float32), np.zeros((1, 8, 3), np.float32), np.zeros(1, np.int64), grid, 0.5
    )
    pts = np.array([[0.1, 0.6, 0.1]], np.float32)
    radar_confidence_packed(pts, np.zeros((8, *half), np.float32), grid)
    radar_confidence_sparse(pts, np.full((1, 8), 0.9, np.float32), np.zeros(1, np.int64), grid)


@njit(cache=True, inline="always")
def _axis_index(v: np.float32, lo: float, inv: float, n: int) -> int:
    """Voxel index of coordinate ``v`` on one axis: ``floor((float64(v) - lo) * inv)`` clamped into
    ``[0, n - 1]`` (the voxelizer's rule 2)."""
    return min(max(int(np.floor((np.float64(v) - lo) * inv)), 0), n - 1)


@njit(cache=True)
def _radar_confidence_sparse_kernel(
    points: np.ndarray,
    occupancy: np.ndarray,
    voxels: np.ndarray,
    lo: np.ndarray,
    inv: np.ndarray,
    shape_xyz: np.ndarray,
) -> np.ndarray:
    """points (K, >=3) float32, occupancy (N, 8), voxels (N,) int64 linear half-scale indices ->
    (K,) float32 neighbourhood max (0 under half-scale voxels not in ``voxels``)."""
    w, h, d = shape_xyz[0], shape_xyz[1], shape_xyz[2]
    w2, h2, d2 = (w + 1) // 2, (h + 1) // 2, (d + 1) // 2
    row = np.full(d2 * h2 * w2, -1, np.int64)  # half-scale linear index -> row of the head output
    for r in range(voxels.shape[0]):
        row[voxels[r]] = r
    out = np.zeros(points.shape[0], np.float32)
    for k in range(points.shape[0]):
        x0 = _axis_index(points[k, 0], lo[0], inv[0], w)
        y0 = _axis_index(points[k, 1], lo[1], inv[1], h)
        z0 = _axis_index(points[k, 2], lo[2], inv[2], d)
        best = np.float32(0.0)
        for z in range(max(z0 - 1, 0), min(z0 + 2, d)):
            for y in range(max(y0 - 1, 0), min(y0 + 2, h)):
                for x in range(max(x0 - 1, 0), min(x0 + 2, w)):
                    r = row[((z >> 1) * h2 + (y >> 1)) * w2 + (x >> 1)]
                    if r >= 0:
                        best = max(best, occupancy[r, ((z & 1) * 2 + (y & 1)) * 2 + (x & 1)])
        out[k] = best
    return out


def _radar_points(points: np.ndarray) -> np.ndarray:
    pts = np.ascontiguousarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (K, >=3) [x, y, z, ...], got shape {pts.shape}")
    return pts


def radar_confidence_packed(points: np.ndarray, occupancy: np.ndarray, grid: GridConfig) -> np.ndarray:
    """points: (K, >=3) [x, y, z, ...] radar rows inside the grid box; occupancy: (8, D2, H2, W2)
    float32 the dense head's packed output -> (K,) float32 confidence (module docstring)."""
    pts = _radar_points(points)
    occ = np.ascontiguousarray(occupancy, dtype=np.float32)
    half = packed_shape(grid)
    if occ.shape != (8, *half):
        raise ValueError(f"packed occupancy must be (8, *{half}), got {occ.shape}")
    lo, _, size, shape = grid_arrays(grid)
    # every half-scale voxel present: the sparse kernel over the (N, 8) view of the packed volume
    rows = occ.reshape(8, -1).T  # (D2 * H2 * W2, 8), a view: row = linear half-scale index
    return _radar_confidence_sparse_kernel(pts, rows, np.arange(rows.shape[0]), lo, 1.0 / size, shape)


def radar_confidence_sparse(
    points: np.ndarray, occupancy: np.ndarray, voxels: np.ndarray, grid: GridConfig
) -> np.ndarray:
    """points: (K, >=3) [x, y, z, ...] radar rows inside the grid box; occupancy (N, 8) float32 and
    voxels (N,) int64 the coarse-to-fine head's output (``decode_sparse``) -> (K,) float32
    confidence (module docstring). Raises ValueError on mismatched shapes or an index outside the
    half-scale grid."""
    pts = _radar_points(points)
    occ = np.ascontiguousarray(occupancy, dtype=np.float32)
    vox = np.ascontiguousarray(voxels, dtype=np.int64)
    n = vox.shape[0] if vox.ndim == 1 else -1
    if occ.shape != (n, 8):
        raise ValueError(f"sparse occupancy must be (N, 8) with voxels (N,); got {occ.shape}, {vox.shape}")
    half = packed_shape(grid)
    if n and (vox.min() < 0 or vox.max() >= half[0] * half[1] * half[2]):
        raise ValueError(f"voxel index outside the half-scale grid {half}")
    lo, _, size, shape = grid_arrays(grid)
    return _radar_confidence_sparse_kernel(pts, occ, vox, lo, 1.0 / size, shape)
