"""Sparse-convolution rulebooks (neighbour tables) from voxel coordinates alone, in numba.

Coordinates are batched: ``coords (V, 4) int32 [b, z, y, x]``, b = sample index in the batch,
rows sorted ascending by ``(b, ((z * H) + y) * W + x)`` and unique (``voxelize`` output per sample,
joined by :func:`batch_coords`).

Kernel 3x3x3; tap ``k = (kz * 3 + ky) * 3 + kx`` with ``kz, ky, kx`` in ``0..2``.

Rule semantics (torch training and the ONNX graph both rely on them):

- ``rules`` is ``(M, 27) int32``: ``rules[o, k]`` is the input row feeding output ``o`` through tap
  ``k``, or the sentinel ``V`` (= number of input rows) where no input voxel sits there. The
  network appends one zero row to the input features, so a layer is exactly
  ``cat(feats (V, C), zeros (1, C))[rules].reshape(M, 27 * C) @ W.reshape(27 * C, C_out)``
  (ONNX: Gather + Reshape + MatMul), with ``W[k, c_in, c_out]`` the weight of tap ``k``.
- Submanifold (``subm_rulebook``): outputs are the inputs (same rows, same order); tap ``k`` of
  output ``i`` reads the input at ``coords[i] + (kz - 1, ky - 1, kx - 1)``, same b.
- Strided (``down_rulebook``, regular sparse conv): output ``o`` exists iff some input sits at
  ``o * stride - padding + (kz, ky, kx)`` for some tap; outputs are sorted like the inputs and
  ``rules[o, k]`` reads the input at ``o * stride - padding + (kz, ky, kx)``. Output shape per axis:
  ``floor((n + 2 * padding - 3) / stride) + 1``.

Algorithm, O(V): voxels sharing ``(b, z, y)`` form a contiguous "row" of the sorted table. The
input row an output row needs through a ``(kz, ky)`` offset only grows with the output row, so
one pointer per offset walks the input rows (a merge, no search). The matching input row is
scattered into a line indexed by x, and the 3 ``kx`` taps of every output voxel of the row are
read from it. Strided outputs are found the same way: candidate output rows from the input rows
(radix-sorted), then per output row the union of the x' its input rows reach. No dense grid is
allocated.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from msdnet.runtime.engine.voxelize import bit_length, radix_sort
from msdnet.runtime.model.onnx_spec import NUM_DOWN
from msdnet.runtime.spec.grid import GridConfig

KERNEL_TAPS = 27  # 3 x 3 x 3 taps: the width of every rules table


@dataclass(frozen=True, eq=False)
class EncoderRulebooks:
    """Every rulebook of the sparse encoder, level 0 (input voxels) to level L (1 / 2**L grid)."""

    coords: tuple[np.ndarray, ...]  # per level l = 0..L: (V_l, 4) int32 [b, z, y, x], sorted
    shapes: tuple[tuple[int, int, int], ...]  # per level: dense (D, H, W) of that level's grid
    subm: tuple[np.ndarray, ...]  # per level: (V_l, 27) int32 rows of level l, sentinel V_l
    down: tuple[np.ndarray, ...]  # per down layer l: (V_{l+1}, 27) int32 rows of level l, sentinel V_l


@njit(cache=True)
def _row_starts(coords: np.ndarray) -> np.ndarray:
    """coords (V, 4) sorted -> (R + 1,) int64 start of each (b, z, y) run, then V."""
    n = coords.shape[0]
    starts = np.empty(n + 1, np.int64)
    r = 0
    for i in range(n):
        if (
            i == 0
            or coords[i, 0] != coords[i - 1, 0]
            or coords[i, 1] != coords[i - 1, 1]
            or coords[i, 2] != coords[i - 1, 2]
        ):
            starts[r] = i
            r += 1
    starts[r] = n
    return starts[: r + 1]


@njit(cache=True)
def _row_keys(coords: np.ndarray, starts: np.ndarray, d: int, h: int) -> np.ndarray:
    """(R,) int64 row keys ``(b * D + z) * H + y`` of the rows starting at ``starts[:-1]``."""
    keys = np.empty(starts.size - 1, np.int64)
    for r in range(starts.size - 1):
        i = starts[r]
        keys[r] = (np.int64(coords[i, 0]) * d + coords[i, 1]) * h + coords[i, 2]
    return keys


@njit(cache=True)
def _find_row(keys: np.ndarray, ptr: int, target: int) -> int:
    """Advance ``ptr`` over the sorted row keys to the first key >= target; return it."""
    while ptr < keys.size and keys[ptr] < target:
        ptr += 1
    return ptr


@njit(cache=True)
def _rules_kernel(
    in_coords: np.ndarray, in_shape: np.ndarray, out_coords: np.ndarray, stride: int, padding: int
) -> np.ndarray:
    """Generic rulebook: rules (M, 27) int32; rules[o, k] = input row at
    out_coords[o] * stride - padding + (kz, ky, kx) (same b), else V. in_shape: (3,) int64 (D, H, W).

    Output rows outermost (their 27 rules stay in cache); per (kz, ky) a pointer walks the input
    rows, since the input row an output row needs only grows with it. The x line holds the
    sentinel where no input sits and is padded, so the 3 kx taps are copied without branches."""
    d_in, h_in, w_in = in_shape[0], in_shape[1], in_shape[2]
    n_in = in_coords.shape[0]
    n_out = out_coords.shape[0]
    rules = np.empty((n_out, KERNEL_TAPS), np.int32)
    if n_in == 0:
        rules[:] = n_in
        return rules
    in_starts = _row_starts(in_coords)
    in_keys = _row_keys(in_coords, in_starts, d_in, h_in)
    out_starts = _row_starts(out_coords)
    ptr = np.zeros(9, np.int64)  # per (kz, ky): current input row
    # line[x + padding] = input row at x of the scattered input row, else n_in; outputs inside
    # the output grid reach x in [-padding, w_in + padding - 1].
    line = np.full(w_in + 2 * padding + 1, n_in, np.int32)
    for r in range(out_starts.size - 1):
        o0, o1 = out_starts[r], out_starts[r + 1]
        b = np.int64(out_coords[o0, 0])
        for kk in range(9):
            zi = np.int64(out_coords[o0, 1]) * stride - padding + kk // 3
            yi = np.int64(out_coords[o0, 2]) * stride - padding + kk % 3
            found = False
            if 0 <= zi < d_in and 0 <= yi < h_in:
                target = (b * d_in + zi) * h_in + yi
                p = _find_row(in_keys, ptr[kk], target)
                ptr[kk] = p
                found = p < in_keys.size and in_keys[p] == target
            if not found:
                for o in range(o0, o1):
                    for kx in range(3):
                        rules[o, kk * 3 + kx] = n_in
                continue
            for j in range(in_starts[p], in_starts[p + 1]):
                line[in_coords[j, 3] + padding] = j
            for o in range(o0, o1):
                xb = np.int64(out_coords[o, 3]) * stride  # line index of tap kx = 0
                for kx in range(3):
                    rules[o, kk * 3 + kx] = line[xb + kx]
            for j in range(in_starts[p], in_starts[p + 1]):
                line[in_coords[j, 3] + padding] = n_in
    return rules


@njit(cache=True)
def _reach(n_in: int, n_out: int, stride: int, padding: int) -> tuple[np.ndarray, np.ndarray]:
    """Per input index i along one axis, the output indices o with o * stride - padding + k == i
    for some k in 0..2 and 0 <= o < n_out: the range first[i] .. last[i] (empty if last < first)."""
    first = np.empty(n_in, np.int64)
    last = np.empty(n_in, np.int64)
    for i in range(n_in):
        # o * stride in [i + padding - 2, i + padding]
        first[i] = max((i + padding - 2 + stride - 1) // stride, 0) if i + padding >= 2 else 0
        last[i] = min((i + padding) // stride, n_out - 1)
    return first, last


@njit(cache=True)
def _down_coords_kernel(
    in_coords: np.ndarray, in_shape: np.ndarray, out_shape: np.ndarray, stride: int, padding: int
) -> np.ndarray:
    """Output voxels of a strided 3x3x3 conv: (V', 4) int32 [b, z, y, x] sorted, unique.

    Candidate output rows come from the input rows (sorted, deduplicated); each output row then
    collects the x' reached from its (up to 9) input rows in a mark line, in ascending order.
    in_shape, out_shape: (3,) int64 (D, H, W)."""
    d_in, h_in, w_in = in_shape[0], in_shape[1], in_shape[2]
    d_out, h_out, w_out = out_shape[0], out_shape[1], out_shape[2]
    n_in = in_coords.shape[0]
    z_first, z_last = _reach(d_in, d_out, stride, padding)
    y_first, y_last = _reach(h_in, h_out, stride, padding)
    x_first, x_last = _reach(w_in, w_out, stride, padding)
    in_starts = _row_starts(in_coords)
    in_keys = _row_keys(in_coords, in_starts, d_in, h_in)
    n_batch = 0
    for i in range(n_in):
        n_batch = max(n_batch, np.int64(in_coords[i, 0]) + 1)
    # Output rows: every (b, z', y') that some input row reaches, sorted, with repeats.
    cand = np.empty(in_keys.size * 9, np.int64)
    m = 0
    for r in range(in_keys.size):
        i = in_starts[r]
        b, z, y = np.int64(in_coords[i, 0]), in_coords[i, 1], in_coords[i, 2]
        for zo in range(z_first[z], z_last[z] + 1):
            for yo in range(y_first[y], y_last[y] + 1):
                cand[m] = (b * d_out + zo) * h_out + yo
                m += 1
    rows = radix_sort(cand[:m], 0, bit_length(n_batch * d_out * h_out - 1))
    # Per output row: the union of the x' its input rows reach.
    most = 1  # most outputs one input reaches per axis, cubed
    for _ in range(3):
        most *= (3 + stride - 1) // stride
    out = np.empty((n_in * most, 4), np.int32)
    n_out = 0
    mark = np.zeros(w_out, np.bool_)
    xs = np.empty(w_out, np.int64)
    ptr = np.zeros(9, np.int64)  # per (kz, ky): current input row
    for t in range(m):
        if t > 0 and rows[t] == rows[t - 1]:
            continue
        b = rows[t] // (d_out * h_out)
        zo = (rows[t] // h_out) % d_out
        yo = rows[t] % h_out
        cnt = 0
        lo, hi = w_out, -1  # span of the marked x'
        for kk in range(9):
            zi = zo * stride - padding + kk // 3
            yi = yo * stride - padding + kk % 3
            if zi < 0 or zi >= d_in or yi < 0 or yi >= h_in:
                continue
            target = (b * d_in + zi) * h_in + yi
            p = _find_row(in_keys, ptr[kk], target)
            ptr[kk] = p
            if p == in_keys.size or in_keys[p] != target:
                continue
            for j in range(in_starts[p], in_starts[p + 1]):
                x = in_coords[j, 3]
                for xo in range(x_first[x], x_last[x] + 1):
                    if not mark[xo]:
                        mark[xo] = True
                        xs[cnt] = xo
                        cnt += 1
                        lo = min(lo, xo)
                        hi = max(hi, xo)
        if hi - lo < 4 * cnt:  # dense row: read the marks in order, O(span)
            cnt = 0
            for xo in range(lo, hi + 1):
                if mark[xo]:
                    xs[cnt] = xo
                    cnt += 1
        else:  # sparse row: insertion sort of the few x', O(cnt^2) with cnt < span / 4
            for a in range(1, cnt):
                v = xs[a]
                q = a - 1
                while q >= 0 and xs[q] > v:
                    xs[q + 1] = xs[q]
                    q -= 1
                xs[q + 1] = v
        for a in range(cnt):
            out[n_out, 0], out[n_out, 1], out[n_out, 2], out[n_out, 3] = b, zo, yo, xs[a]
            n_out += 1
            mark[xs[a]] = False
    return out[:n_out].copy()


@njit(cache=True)
def _coords_error(coords: np.ndarray, shape: np.ndarray) -> int:
    """0 if coords (V, 4) [b, z, y, x] lie in the grid with b >= 0 and are strictly ascending by
    (b, linear index); 1 if outside; 2 if unsorted or repeated."""
    d, h, w = shape[0], shape[1], shape[2]
    prev = np.int64(-1)
    for i in range(coords.shape[0]):
        b, z, y, x = coords[i, 0], coords[i, 1], coords[i, 2], coords[i, 3]
        if b < 0 or z < 0 or z >= d or y < 0 or y >= h or x < 0 or x >= w:
            return 1
        key = ((np.int64(b) * d + z) * h + y) * w + x
        if key <= prev:
            return 2
        prev = key
    return 0


def _check_coords(coords: np.ndarray, shape_zyx: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Validate (V, 4) [b, z, y, x] sorted unique coords inside shape; return int32 coords and
    (3,) int64 shape. Raises ValueError."""
    shape = np.asarray(tuple(int(s) for s in shape_zyx), dtype=np.int64)
    if shape.shape != (3,) or np.any(shape < 1):
        raise ValueError(f"shape_zyx must be 3 positive ints (D, H, W), got {tuple(shape_zyx)}")
    c = np.ascontiguousarray(coords, dtype=np.int32)
    if c.ndim != 2 or c.shape[1] != 4:
        raise ValueError(f"coords must be (V, 4) [b, z, y, x], got shape {c.shape}")
    err = _coords_error(c, shape)
    if err == 1:
        raise ValueError(f"coords outside batch >= 0 and grid {tuple(shape.tolist())}")
    if err == 2:
        raise ValueError("coords must be unique and sorted by (b, linear index)")
    return c, shape


def down_shape(shape_zyx: Sequence[int], stride: int = 2, padding: int = 1) -> tuple[int, int, int]:
    """Output (D', H', W') of a 3x3x3 conv: floor((n + 2 * padding - 3) / stride) + 1 per axis."""
    out = tuple((int(n) + 2 * padding - 3) // stride + 1 for n in shape_zyx)
    if len(out) != 3 or min(out) < 1:
        raise ValueError(f"grid {tuple(shape_zyx)} too small for stride {stride}, padding {padding}")
    return out  # type: ignore[return-value]


def level_shapes(grid: GridConfig, num_down: int = NUM_DOWN) -> list[tuple[int, int, int]]:
    """Dense (D, H, W) of encoder levels 0..num_down (level l is 1 / 2**l of the grid)."""
    shapes = [tuple(grid.shape_zyx)]
    for _ in range(num_down):
        shapes.append(down_shape(shapes[-1]))
    return shapes  # type: ignore[return-value]


def subm_rulebook(coords: np.ndarray, shape_zyx: Sequence[int]) -> np.ndarray:
    """Submanifold 3x3x3 rulebook. coords: (V, 4) int32 [b, z, y, x] sorted -> (V, 27) int32,
    rules[i, k] = row at coords[i] + (kz-1, ky-1, kx-1), else V (see module docstring)."""
    c, shape = _check_coords(coords, shape_zyx)
    return _rules_kernel(c, shape, c, 1, 1)


def down_rulebook(
    coords: np.ndarray, shape_zyx: Sequence[int], stride: int = 2, padding: int = 1
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """Strided 3x3x3 sparse conv. coords: (V, 4) int32 [b, z, y, x] sorted ->
    (out_coords (V', 4) int32 sorted, rules (V', 27) int32 rows of coords or V, out_shape_zyx)."""
    if stride < 1 or padding < 0:
        raise ValueError(f"stride must be >= 1 and padding >= 0, got {stride}, {padding}")
    c, shape = _check_coords(coords, shape_zyx)
    out_shape = down_shape(shape_zyx, stride, padding)
    out_coords = _down_coords_kernel(c, shape, np.asarray(out_shape, np.int64), stride, padding)
    rules = _rules_kernel(c, shape, out_coords, stride, padding)
    return out_coords, rules, out_shape


def build_encoder_rulebooks(
    coords: np.ndarray, shape_zyx: Sequence[int], num_down: int = 3
) -> EncoderRulebooks:
    """All rulebooks of the encoder: subm at levels 0..num_down, stride-2 down between them.

    coords: (V, 4) int32 [b, z, y, x] sorted (level 0 = the input voxels); shape_zyx: (D, H, W).
    """
    if num_down < 0:
        raise ValueError(f"num_down must be >= 0, got {num_down}")
    c, _ = _check_coords(coords, shape_zyx)
    levels, shapes = [c], [tuple(int(s) for s in shape_zyx)]
    subm, down = [], []
    for level in range(num_down + 1):
        in_shape = np.asarray(shapes[level], np.int64)
        subm.append(_rules_kernel(levels[level], in_shape, levels[level], 1, 1))
        if level == num_down:
            break
        out_shape = down_shape(shapes[level])
        out = _down_coords_kernel(levels[level], in_shape, np.asarray(out_shape, np.int64), 2, 1)
        down.append(_rules_kernel(levels[level], in_shape, out, 2, 1))
        levels.append(out)
        shapes.append(out_shape)
    return EncoderRulebooks(tuple(levels), tuple(shapes), tuple(subm), tuple(down))


def batch_coords(coords_list: Sequence[np.ndarray]) -> np.ndarray:
    """Join per-sample voxel coords: list of (V_i, 3) int [z, y, x], each sorted by linear index
    (as ``voxelize`` returns them) -> (sum V_i, 4) int32 [b, z, y, x], b = position in the list."""
    parts = []
    for b, c in enumerate(coords_list):
        c = np.asarray(c)
        if c.ndim != 2 or c.shape[1] != 3:
            raise ValueError(f"sample {b}: coords must be (V, 3) [z, y, x], got shape {c.shape}")
        part = np.empty((c.shape[0], 4), np.int32)  # (V_i, 4) [b, z, y, x]
        part[:, 0] = b
        part[:, 1:] = c
        parts.append(part)
    if not parts:
        return np.empty((0, 4), np.int32)
    return np.concatenate(parts, axis=0)


def warmup() -> None:
    """Compile (or load from numba's cache) the rulebook kernels with a tiny input."""
    coords = np.array([[0, 0, 0, 0], [0, 0, 0, 1], [0, 1, 1, 1], [1, 0, 0, 0]], np.int32)
    build_encoder_rulebooks(coords, (2, 2, 2), num_down=1)
