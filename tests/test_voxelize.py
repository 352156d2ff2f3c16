"""Numba voxelizer against the numpy reference and against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from msdnet.benchmarks.cli import main
from msdnet.benchmarks.numpy_reference import voxelize_numpy
from msdnet.benchmarks.voxelize_bench import format_table, run_voxelize_bench
from msdnet.runtime.engine.kernels import warmup
from msdnet.runtime.engine.voxelize import Voxels, voxelize
from msdnet.runtime.spec.grid import GRID_PRESETS, GridConfig

TINY = GRID_PRESETS["tiny"]  # 32 x 32 x 10, range [0, 12.8] x [-6.4, 6.4] x [-2, 4]


def assert_same(a: Voxels, b: Voxels) -> None:
    np.testing.assert_array_equal(a.coords, b.coords)
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_array_equal(a.features, b.features)
    assert a.dropped_out_of_range == b.dropped_out_of_range
    assert a.dropped_over_cap == b.dropped_over_cap
    assert a.coords.dtype == np.int32 and a.counts.dtype == np.int32
    assert a.features.dtype == np.float32


def linear(coords: np.ndarray, grid: GridConfig) -> np.ndarray:
    """(V, 3) [z, y, x] -> (V,) linear index."""
    _, h, w = grid.shape_zyx
    c = coords.astype(np.int64)
    return (c[:, 0] * h + c[:, 1]) * w + c[:, 2]


def test_warmup_then_two_points_in_one_voxel() -> None:
    warmup()  # compiles every kernel once so the rest of the suite is fast
    pts = np.array([[0.1, -6.3, -1.9, 1.0], [0.3, -6.1, -1.5, 3.0], [12.7, 6.3, 3.9, 5.0]], np.float32)
    v = voxelize(pts, TINY, max_voxels=10)
    np.testing.assert_array_equal(v.coords, [[0, 0, 0], [9, 31, 31]])
    np.testing.assert_array_equal(v.counts, [2, 1])
    np.testing.assert_allclose(v.features[0], [0.2, -6.2, -1.7, 2.0], rtol=1e-6)
    np.testing.assert_array_equal(v.features[1], pts[2])
    assert (v.dropped_out_of_range, v.dropped_over_cap) == (0, 0)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 3000),
    columns=st.integers(3, 7),
    preset=st.sampled_from(["tiny", "lite"]),
    spread=st.sampled_from([0.0, 0.3, 1.0]),  # 0: every point in a few voxels
    cap=st.integers(1, 5000),
)
def test_matches_numpy_reference(
    seed: int, n: int, columns: int, preset: str, spread: float, cap: int
) -> None:
    grid = GRID_PRESETS[preset]
    rng = np.random.default_rng(seed)
    lo, hi = np.array(grid.point_range[:3]), np.array(grid.point_range[3:])
    margin = 0.1 * (hi - lo)
    centres = rng.uniform(lo - margin, hi + margin, size=(max(1, int(spread * n)), 3))
    xyz = centres[rng.integers(0, len(centres), n)] + rng.normal(0, 0.05, (n, 3))
    pts = np.concatenate([xyz, rng.normal(size=(n, columns - 3))], axis=1).astype(np.float32)
    if n:
        pts[rng.integers(0, n, max(1, n // 50))] = np.nan  # a few NaN rows
        if columns > 3:
            pts[rng.integers(0, n, max(1, n // 50)), columns - 1] = np.inf  # bad feature only
    v = voxelize(pts, grid, cap)
    assert_same(v, voxelize_numpy(pts, grid, cap))
    assert np.all(np.diff(linear(v.coords, grid)) > 0)  # strictly ascending linear index
    assert v.counts.sum() + v.dropped_out_of_range + v.dropped_over_cap == n


def test_empty_cloud() -> None:
    v = voxelize(np.empty((0, 5), np.float32), TINY, 100)
    assert v.coords.shape == (0, 3) and v.counts.shape == (0,) and v.features.shape == (0, 5)
    assert (v.dropped_out_of_range, v.dropped_over_cap) == (0, 0)


def test_every_point_in_one_voxel() -> None:
    rng = np.random.default_rng(1)
    pts = np.concatenate(
        [rng.uniform((4.01, 0.01, -0.19), (4.39, 0.39, 0.39), (5000, 3)), rng.normal(size=(5000, 2))],
        axis=1,
    ).astype(np.float32)
    v = voxelize(pts, TINY, 1)
    np.testing.assert_array_equal(v.coords, [[3, 16, 10]])  # z=(0-(-2))/0.6, y=6.4/0.4, x=4/0.4
    assert v.counts.tolist() == [5000]
    np.testing.assert_allclose(v.features[0], pts.astype(np.float64).mean(axis=0), rtol=1e-6)


def test_range_is_half_open() -> None:
    grid = GridConfig((0.0, -8.0, -2.0, 16.0, 8.0, 4.0), (0.5, 0.5, 0.75))  # float32-exact bounds
    lo = np.array(grid.point_range[:3], np.float32)
    hi = np.array(grid.point_range[3:], np.float32)
    below_hi = np.nextafter(hi, np.float32(-np.inf))  # largest float32 under each upper bound
    pts = np.stack([lo, hi, below_hi, np.where([True, False, False], hi, lo)]).astype(np.float32)
    v = voxelize(pts, grid, 10)
    np.testing.assert_array_equal(v.coords, [[0, 0, 0], [7, 31, 31]])  # lo -> first, hi - ulp -> last
    assert v.dropped_out_of_range == 2  # hi on every axis, hi on x only
    assert_same(v, voxelize_numpy(pts, grid, 10))


def test_non_finite_rows_dropped() -> None:
    pts = np.array(
        [
            [1.0, 0.0, 0.0, 1.0],
            [np.nan, 0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0, np.nan],  # NaN only in a feature column
            [1.0, 0.0, 0.0, np.inf],
            [1.0, -np.inf, 0.0, 1.0],
        ],
        np.float32,
    )
    v = voxelize(pts, TINY, 10)
    assert v.counts.tolist() == [1] and v.dropped_out_of_range == 4
    np.testing.assert_array_equal(v.features, pts[:1])
    assert_same(v, voxelize_numpy(pts, TINY, 10))


def test_cap_keeps_fullest_voxels_ties_to_lower_index() -> None:
    # voxels along x at z=0, y=0 with point counts 2, 3, 1, 3, 2 (x = 0..4)
    counts = [2, 3, 1, 3, 2]
    xs = np.repeat(np.arange(5) * 0.4 + 0.2, counts)
    pts = np.stack([xs, np.full_like(xs, -6.2), np.full_like(xs, -1.7)], axis=1).astype(np.float32)
    v = voxelize(pts, TINY, 3)
    assert v.coords[:, 2].tolist() == [0, 1, 3]  # 3, 3 and the first of the 2s, in x order
    assert v.counts.tolist() == [2, 3, 3]
    assert v.dropped_over_cap == 1 + 2 and v.dropped_out_of_range == 0
    assert_same(v, voxelize_numpy(pts, TINY, 3))
    assert voxelize(pts, TINY, 5).dropped_over_cap == 0


def test_input_is_cast_and_checked() -> None:
    pts = np.array([[1.0, 0.0, 0.0]], np.float64)
    assert voxelize(pts, TINY, 1).features.dtype == np.float32
    with pytest.raises(ValueError, match="points must be"):
        voxelize(np.zeros((4, 2), np.float32), TINY, 10)
    with pytest.raises(ValueError, match="max_voxels"):
        voxelize(pts, TINY, 0)


def test_benchmark_runs_on_small_inputs() -> None:
    rows = run_voxelize_bench(
        1, point_counts=(300, 2000), rulebook_voxels=500, grids=("tiny",), big_grid="lite"
    )
    assert [(r.case, r.size) for r in rows[:2]] == [("voxelize", 300), ("voxelize", 2000)]
    assert rows[2].case.startswith("rulebooks") and rows[2].size == 500
    assert rows[3].case.startswith("decode") and rows[3].size == 20 * 160 * 160
    assert all(r.numba_ms > 0 and r.numpy_ms > 0 for r in rows)
    table = format_table(rows)
    assert "speedup" in table and len(table.splitlines()) == 2 + len(rows)
    result = CliRunner().invoke(main, ["voxelize", "--repeats", "0"])
    assert result.exit_code == 2 and "--repeats" in result.output
