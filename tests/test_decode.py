"""Occupancy decoder against the numpy reference and hand-computed voxel centres."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msdnet.benchmarks.numpy_reference import decode_numpy
from msdnet.runtime.engine.decode import decode_occupancy, decode_packed, unpack_children, warmup
from msdnet.runtime.spec.grid import GRID_PRESETS, GridConfig

TINY = GRID_PRESETS["tiny"]  # (D, H, W) = (10, 32, 32)


def test_warmup_then_one_voxel() -> None:
    warmup()  # compiles the kernel once so the rest of the suite is fast
    occ = np.zeros(TINY.shape_zyx, np.float32)
    off = np.zeros((3, *TINY.shape_zyx), np.float32)
    occ[2, 5, 7] = 0.75
    off[:, 2, 5, 7] = (0.1, -0.05, 0.2)  # [dx, dy, dz]
    points, conf = decode_occupancy(occ, off, TINY, 0.5)
    # centre: x = 0 + 7.5 * 0.4, y = -6.4 + 5.5 * 0.4, z = -2 + 2.5 * 0.6
    np.testing.assert_allclose(points, [[3.0 + 0.1, -4.2 - 0.05, -0.5 + 0.2]], atol=1e-6)
    assert points.dtype == np.float32 and conf.tolist() == [0.75]
    np.testing.assert_allclose(TINY.voxel_centres(np.array([[2, 5, 7]])), [[3.0, -4.2, -0.5]], atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    threshold=st.floats(0.0, 1.0),
    density=st.floats(0.0, 1.0),
    grid=st.sampled_from([TINY, GridConfig((-3.0, -2.5, -1.0, 9.0, 2.5, 1.7), (0.25, 0.1, 0.3))]),
)
def test_matches_numpy_reference(seed: int, threshold: float, density: float, grid: GridConfig) -> None:
    rng = np.random.default_rng(seed)
    occ = (rng.uniform(size=grid.shape_zyx) * density).astype(np.float32)
    occ[rng.uniform(size=occ.shape) < 0.01] = np.float32(threshold)  # ties are not kept
    off = rng.uniform(-0.1, 0.1, size=(3, *grid.shape_zyx)).astype(np.float32)
    points, conf = decode_occupancy(occ, off, grid, threshold)
    ref_points, ref_conf = decode_numpy(occ, off, grid, threshold)
    np.testing.assert_array_equal(points, ref_points)
    np.testing.assert_array_equal(conf, ref_conf)
    assert np.all(conf > np.float32(threshold))
    assert len(conf) == int((occ > np.float32(threshold)).sum())


def test_order_is_linear_index_and_empty_output() -> None:
    grid = GridConfig((0.0, 0.0, 0.0, 2.0, 2.0, 2.0), (1.0, 1.0, 1.0))  # 2 x 2 x 2
    occ = np.arange(8, dtype=np.float32).reshape(2, 2, 2) / 10  # (D, H, W)
    off = np.zeros((3, 2, 2, 2), np.float32)
    points, conf = decode_occupancy(occ, off, grid, 0.45)
    np.testing.assert_allclose(conf, [0.5, 0.6, 0.7])  # linear indices 5, 6, 7
    np.testing.assert_array_equal(points, [[1.5, 0.5, 1.5], [0.5, 1.5, 1.5], [1.5, 1.5, 1.5]])
    points, conf = decode_occupancy(occ, off, grid, 1.0)
    assert points.shape == (0, 3) and conf.shape == (0,)


def test_shapes_are_checked() -> None:
    occ = np.zeros(TINY.shape_zyx, np.float32)
    with pytest.raises(ValueError, match="occupancy must be"):
        decode_occupancy(occ[1:], np.zeros((3, 9, 32, 32), np.float32), TINY, 0.5)
    with pytest.raises(ValueError, match="offsets must be"):
        decode_occupancy(occ, np.zeros((2, *TINY.shape_zyx), np.float32), TINY, 0.5)


def _pack(dense: np.ndarray) -> np.ndarray:
    """(..., D, H, W) dense -> (8, ..., D2, H2, W2) packed (zero padded to even sizes): the
    inverse of ``unpack_children``, written with explicit strides."""
    *lead, d, h, w = dense.shape
    d2, h2, w2 = (d + 1) // 2, (h + 1) // 2, (w + 1) // 2
    padded = np.zeros((*lead, 2 * d2, 2 * h2, 2 * w2), dense.dtype)
    padded[..., :d, :h, :w] = dense
    out = np.empty((8, *lead, d2, h2, w2), dense.dtype)
    for dz in range(2):
        for dy in range(2):
            for dx in range(2):
                out[(dz * 2 + dy) * 2 + dx] = padded[..., dz::2, dy::2, dx::2]
    return out


@pytest.mark.parametrize("grid", [TINY, GridConfig((0.0, 0.0, 0.0, 1.4, 1.0, 0.6), (0.2, 0.2, 0.2))])
def test_packed_decoder_equals_dense_decoder(grid):
    """Odd and even grids: the packed layout decodes to the same points, in the same order."""
    rng = np.random.default_rng(3)
    occ = rng.random(grid.shape_zyx, dtype=np.float32)
    off = rng.uniform(-0.1, 0.1, (3, *grid.shape_zyx)).astype(np.float32)
    p_occ, p_off = _pack(occ), _pack(off)
    np.testing.assert_array_equal(unpack_children(p_occ, grid.shape_zyx), occ)
    np.testing.assert_array_equal(unpack_children(p_off, grid.shape_zyx), off)
    ref_pts, ref_conf = decode_occupancy(occ, off, grid, 0.7)
    pts, conf = decode_packed(p_occ, p_off, grid, 0.7)
    assert len(pts) > 0
    np.testing.assert_array_equal(pts, ref_pts)
    np.testing.assert_array_equal(conf, ref_conf)
    with pytest.raises(ValueError, match="packed occupancy"):
        decode_packed(occ, off, grid, 0.7)
