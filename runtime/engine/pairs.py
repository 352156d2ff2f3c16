"""Neighbour pairs for the pair form of the sparse encoder (``encoder_form`` "pairs").

The rulebook form reads, for every output voxel, all 27 kernel taps (a sentinel zero row where no
input voxel sits) and multiplies them in one GEMM. The pair form touches only the real
(input row, output row) pairs of each tap: gather the input rows, multiply by the tap's weight,
scatter-add into the output rows. The taps of a layer share one batched GEMM (a group, padded to
its largest tap's count); every tap is then scattered on its own, so no scatter sees an output
row twice (onnxruntime's CPU ScatterND-add runs its updates in parallel and loses colliding
ones). One group a layer keeps the graph small: on 2 cores onnxruntime's cost per node, not the
padding, decided it (per-tap GEMMs made about 1,470 nodes, 13 mirror-pair groups 1,130).

- submanifold layers: the centre tap is the identity map (a plain GEMM); the other 26 taps form
  the group (tap ``k`` and its mirror ``26 - k`` have equal counts);
- stride-2 layers: each tap reads the input voxels of one parity pattern (odd coordinates on the
  axes where it is off the centre, even elsewhere), so the 27 counts are alike;
- the BEV collapse (a 1x1 conv over ``C x D8`` channels): one tap per height ``z``, each voxel of
  the last level one pair (voxel row -> BEV cell ``y * W8 + x``).

A group's pairs are one int64 array ``(2, taps, P)``: row 0 the input rows, row 1 the output
rows, ``P`` the group's largest count; shorter taps are padded with the input sentinel (the
zero row the graph appends) and the output dummy row (the extra row the graph drops), whose
products are exactly zero.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from msdnet.runtime.engine.rulebook import KERNEL_TAPS, EncoderRulebooks

CENTRE = KERNEL_TAPS // 2  # tap 13: offset (0, 0, 0)
SUBM_GROUPS: tuple[tuple[int, ...], ...] = (tuple(k for k in range(KERNEL_TAPS) if k != CENTRE),)
DOWN_GROUPS: tuple[tuple[int, ...], ...] = (tuple(range(KERNEL_TAPS)),)


@njit(cache=True)
def _tap_pairs(rules: np.ndarray, n_in: int, taps: np.ndarray) -> np.ndarray:
    """rules (M, 27) int, sentinel ``n_in`` -> (2, len(taps), P) int64: per tap its real pairs
    [input row; output row] in output order, padded to P = max(1, largest count) with [n_in; M]."""
    m = rules.shape[0]
    counts = np.zeros(taps.size, np.int64)
    for o in range(m):
        for a in range(taps.size):
            if rules[o, taps[a]] < n_in:
                counts[a] += 1
    p = max(1, counts.max()) if taps.size else 1
    out = np.empty((2, taps.size, p), np.int64)
    out[0, :, :] = n_in
    out[1, :, :] = m
    fill = np.zeros(taps.size, np.int64)
    for o in range(m):
        for a in range(taps.size):
            r = rules[o, taps[a]]
            if r < n_in:
                out[0, a, fill[a]] = r
                out[1, a, fill[a]] = o
                fill[a] += 1
    return out


@njit(cache=True)
def _bev_pairs(coords: np.ndarray, d8: int, w8: int, cells: int) -> np.ndarray:
    """coords (V, 4) [b = 0, z, y, x] of the last level -> (2, d8, P) int64: per height z the
    voxel rows at z and their BEV cells ``y * w8 + x``, padded with [V; cells]."""
    n = coords.shape[0]
    counts = np.zeros(d8, np.int64)
    for i in range(n):
        counts[coords[i, 1]] += 1
    p = max(1, counts.max())
    out = np.empty((2, d8, p), np.int64)
    out[0, :, :] = n
    out[1, :, :] = cells
    fill = np.zeros(d8, np.int64)
    for i in range(n):
        z = coords[i, 1]
        out[0, z, fill[z]] = i
        out[1, z, fill[z]] = np.int64(coords[i, 2]) * w8 + coords[i, 3]
        fill[z] += 1
    return out


def layer_names(levels: int) -> list[str]:
    """The encoder's conv layers in order: ``subm_0``, ``down_1``, ``subm_1``, ... ``subm_<levels>``."""
    names = ["subm_0"]
    for level in range(1, levels + 1):
        names += [f"down_{level}", f"subm_{level}"]
    return names


def groups_of(layer: str) -> tuple[tuple[int, ...], ...]:
    """The tap groups of a layer named by :func:`layer_names`."""
    return SUBM_GROUPS if layer.startswith("subm") else DOWN_GROUPS


def pair_feeds(rb: EncoderRulebooks, levels: int) -> dict[str, np.ndarray]:
    """The pair form's inputs from the rulebooks of ``levels`` down layers (``onnx_spec``'s
    ``encoder_pairs_spec``): ``voxel_counts`` (levels + 1,) int64 V_l, then per layer and group
    ``<layer>_pairs_<g>`` (2, taps, P) int64, then ``bev_pairs`` (2, D8, P) int64."""
    feeds: dict[str, np.ndarray] = {
        "voxel_counts": np.asarray([len(rb.coords[level]) for level in range(levels + 1)], np.int64)
    }
    for layer in layer_names(levels):
        kind, level = layer.split("_")
        lv = int(level)
        rules = rb.subm[lv] if kind == "subm" else rb.down[lv - 1]
        n_in = len(rb.coords[lv]) if kind == "subm" else len(rb.coords[lv - 1])
        for g, taps in enumerate(groups_of(layer)):
            feeds[f"{layer}_pairs_{g}"] = _tap_pairs(rules, n_in, np.asarray(taps, np.int64))
    d8, h8, w8 = rb.shapes[levels]
    feeds["bev_pairs"] = _bev_pairs(np.ascontiguousarray(rb.coords[levels]), d8, w8, h8 * w8)
    return feeds


def warmup() -> None:
    """Compile (or load from numba's cache) the pair kernels with a tiny input."""
    _tap_pairs(np.zeros((1, KERNEL_TAPS), np.int32), 1, np.arange(2, dtype=np.int64))
    _bev_pairs(np.zeros((1, 4), np.int32), 1, 1, 1)
