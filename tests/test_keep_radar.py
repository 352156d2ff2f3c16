"""Keeping true radar returns: the radar points' confidence from the head's own output (numba
kernels against a numpy reference), the Pipeline's keep threshold (manifest field, per call) and the
threshold choice (``export.keep``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from export_helpers import copy_artifact, make_artifact

from msdnet.runtime import MsdnetError, Pipeline, PointCloud
from msdnet.runtime.engine.decode import (
    packed_shape,
    radar_confidence_packed,
    radar_confidence_sparse,
    unpack_children,
)
from msdnet.runtime.engine.voxelize import in_range_mask
from msdnet.runtime.model.artifact import load_artifact
from msdnet.runtime.spec.grid import GridConfig


def reference_confidence(points: np.ndarray, dense: np.ndarray, grid: GridConfig) -> np.ndarray:
    """numpy: points (K, >=3), dense full-scale occupancy (D, H, W) (0 where not computed) ->
    (K,) float32 max over the 3 x 3 x 3 voxels around each point's voxel (clipped to the grid)."""
    lo = np.asarray(grid.point_range[:3], np.float64)
    size = np.asarray(grid.voxel_size, np.float64)
    shape_xyz = np.asarray(grid.shape_zyx[::-1])
    idx = np.floor((points[:, :3].astype(np.float64) - lo) * (1.0 / size)).astype(np.int64)
    idx = np.clip(idx, 0, shape_xyz - 1)
    out = np.zeros(len(points), np.float32)
    d, h, w = dense.shape
    for k, (x, y, z) in enumerate(idx):
        win = dense[
            max(z - 1, 0) : min(z + 2, d), max(y - 1, 0) : min(y + 2, h), max(x - 1, 0) : min(x + 2, w)
        ]
        out[k] = win.max()
    return out


GRID = GridConfig((0.0, -1.6, -0.6, 3.2, 1.6, 0.6), (0.2, 0.2, 0.3))  # (D, H, W) = (4, 16, 16)


def _points(rng: np.random.Generator, n: int) -> np.ndarray:
    lo = np.asarray(GRID.point_range[:3], np.float32)
    hi = np.asarray(GRID.point_range[3:], np.float32)
    pts = lo + (hi - lo) * rng.random((n, 3), dtype=np.float32)
    pts[0] = lo  # a corner voxel: the window is clipped
    pts[1] = np.nextafter(hi, lo)  # a hair below the upper faces
    return pts


def test_packed_confidence_matches_numpy():
    rng = np.random.default_rng(0)
    half = packed_shape(GRID)
    occ = rng.random((8, *half), dtype=np.float32)
    pts = _points(rng, 200)
    got = radar_confidence_packed(pts, occ, GRID)
    assert got.dtype == np.float32 and got.shape == (200,)
    np.testing.assert_array_equal(got, reference_confidence(pts, unpack_children(occ, GRID.shape_zyx), GRID))


def test_sparse_confidence_matches_numpy_and_missing_voxels_count_zero():
    rng = np.random.default_rng(1)
    d2, h2, w2 = packed_shape(GRID)
    n_half = d2 * h2 * w2
    voxels = np.sort(rng.choice(n_half, size=n_half // 3, replace=False)).astype(np.int64)
    occ = rng.random((len(voxels), 8), dtype=np.float32)
    # the same values on the dense grid, 0 under the half-scale voxels not listed
    packed = np.zeros((8, n_half), np.float32)
    packed[:, voxels] = occ.T
    dense = unpack_children(packed.reshape(8, d2, h2, w2), GRID.shape_zyx)
    pts = _points(rng, 300)
    got = radar_confidence_sparse(pts, occ, voxels, GRID)
    np.testing.assert_array_equal(got, reference_confidence(pts, dense, GRID))
    # every voxel listed (in any order): the packed kernel's answer
    order = rng.permutation(n_half)
    full = packed.reshape(8, -1).copy()
    full[:, :] = rng.random(full.shape, dtype=np.float32)
    all_sparse = radar_confidence_sparse(pts, full.T[order], order.astype(np.int64), GRID)
    np.testing.assert_array_equal(all_sparse, radar_confidence_packed(pts, full.reshape(8, d2, h2, w2), GRID))
    # no voxel at all: confidence 0 everywhere; no point: empty
    none = radar_confidence_sparse(pts, np.zeros((0, 8), np.float32), np.zeros(0, np.int64), GRID)
    assert not none.any()
    assert radar_confidence_sparse(np.zeros((0, 3), np.float32), occ, voxels, GRID).shape == (0,)


def test_confidence_refuses_bad_shapes():
    half = packed_shape(GRID)
    pts = np.zeros((2, 3), np.float32)
    with pytest.raises(ValueError, match="packed occupancy"):
        radar_confidence_packed(pts, np.zeros((8, 1, 1, 1), np.float32), GRID)
    with pytest.raises(ValueError, match="outside the half-scale grid"):
        radar_confidence_sparse(pts, np.zeros((1, 8), np.float32), np.array([np.prod(half)]), GRID)
    with pytest.raises(ValueError, match=r"\(K, >=3\)"):
        radar_confidence_packed(np.zeros(3, np.float32), np.zeros((8, *half), np.float32), GRID)


# ---------------------------------------------------------------- the Pipeline


@pytest.fixture(scope="module")
def pipe(student_dir) -> Pipeline:
    return Pipeline.from_dir(student_dir, threads=1)


def _radar(pipe: Pipeline, scan: PointCloud) -> np.ndarray:
    arr = scan.select(pipe.columns).points
    return arr[in_range_mask(arr, pipe.artifact.grid), :3]


def test_no_threshold_is_todays_output(pipe, scan):
    assert pipe.artifact.keep_threshold is None and pipe.keep_threshold is None
    res = pipe(scan, steps=2, seed=3)
    assert (
        res.radar_confidence is None and "radar_confident" not in res.stats and "radar_kept" not in res.stats
    )


def test_keep_threshold_on_the_dense_head(pipe, scan):
    grid = pipe.artifact.grid
    base = pipe(scan, steps=2, seed=3)
    dense = unpack_children(pipe._occ[0], grid.shape_zyx)  # the call's full-scale occupancy
    radar = _radar(pipe, scan)
    conf = reference_confidence(radar, dense, grid)
    thr = float(np.quantile(conf, 0.5))  # about half of the radar points kept
    res = pipe(scan, steps=2, seed=3, keep_threshold=thr)
    np.testing.assert_array_equal(res.radar_confidence, conf)
    kept = conf >= np.float32(thr)
    assert 0 < kept.sum() < len(radar)
    m = len(base.points)
    np.testing.assert_array_equal(res.points[:m], base.points)
    np.testing.assert_array_equal(res.confidence[:m], base.confidence)
    np.testing.assert_array_equal(res.points[m:], radar[kept])
    np.testing.assert_array_equal(res.confidence[m:], conf[kept])
    assert res.stats["radar_confident"] == res.stats["radar_kept"] == kept.sum()
    # keep_radar on top: the output without it first, then the radar points not kept (confidence 1)
    both = pipe(scan, steps=2, seed=3, keep_threshold=thr, keep_radar=True)
    np.testing.assert_array_equal(both.points[: len(res.points)], res.points)
    np.testing.assert_array_equal(both.points[len(res.points) :], radar[~kept])
    assert np.all(both.confidence[len(res.points) :] == 1.0)
    assert both.stats["radar_kept"] == len(radar) and both.stats["radar_confident"] == kept.sum()
    # 0 keeps every radar point: the points of keep_radar, in the same order
    everything = pipe(scan, steps=2, seed=3, keep_threshold=0.0)
    np.testing.assert_array_equal(everything.points, pipe(scan, steps=2, seed=3, keep_radar=True).points)
    with pytest.raises(MsdnetError, match="keep_threshold"):
        pipe(scan, keep_threshold=1.5)


def test_keep_threshold_on_the_coarse_to_fine_head(pipe, scan):
    grid = pipe.artifact.grid
    pipe.gate = 0.5
    try:
        res = pipe(scan, steps=2, seed=3, keep_threshold=0.3)
        out = pipe.sparse_head_outputs()
    finally:
        pipe.gate = pipe.artifact.gate
    d2, h2, w2 = packed_shape(grid)
    packed = np.zeros((8, d2 * h2 * w2), np.float32)
    packed[:, out["voxels"]] = out["occupancy"].T
    dense = unpack_children(packed.reshape(8, d2, h2, w2), grid.shape_zyx)
    radar = _radar(pipe, scan)
    conf = reference_confidence(radar, dense, grid)
    np.testing.assert_array_equal(res.radar_confidence, conf)
    np.testing.assert_array_equal(res.points[len(res.points) - res.stats["radar_kept"] :], radar[conf >= 0.3])


def test_manifest_threshold(student_dir, tmp_path, scan):
    d = copy_artifact(student_dir, tmp_path / "keep")
    m = json.loads((d / "manifest.json").read_text())
    (d / "manifest.json").write_text(json.dumps({**m, "keep_radar_threshold": 0.25}))
    p = Pipeline.from_dir(d, threads=1)
    assert p.artifact.keep_threshold == 0.25 and p.keep_threshold == 0.25
    res = p(scan, steps=2, seed=3)
    ref = Pipeline.from_dir(student_dir, threads=1)(scan, steps=2, seed=3, keep_threshold=0.25)
    np.testing.assert_array_equal(res.points, ref.points)
    assert res.stats["radar_confident"] == ref.stats["radar_confident"]
    for bad in (1.5, -0.1, "0.2", True):
        (d / "manifest.json").write_text(json.dumps({**m, "keep_radar_threshold": bad}))
        with pytest.raises(MsdnetError, match="keep_radar_threshold"):
            load_artifact(d)


def test_choose_and_write_the_threshold(student_dir, tmp_path):
    """The pick's test (at least as good as keeping every radar point on the five scene metrics),
    its table, and the manifest fields it writes."""
    from msdnet.export.keep import KeepCalibration, at_least_as_good, calibration_markdown, write_keep

    base = {"cd": 0.7, "mhd": 0.84, "fscore@0.2": 0.198, "fscore@0.5": 0.57, "jsd": 0.4685, "points": 1.0}
    good = {**base, "cd": 0.69, "jsd": 0.4684}
    bad = {**base, "cd": 0.68, "jsd": 0.47}
    assert at_least_as_good(good, base) and not at_least_as_good(bad, base)
    cal = KeepCalibration(0.05, True, ["000299"], table={"model": base, "keep all": base, "0.05": good})
    assert "0.05 (pick)" in calibration_markdown(cal)
    d = copy_artifact(student_dir, tmp_path / "write")
    write_keep(d, cal, "selection slice 000299..000299")
    art = load_artifact(d)
    assert art.keep_threshold == 0.05
    assert art.manifest["keep_radar_calibration"]["split"] == "selection slice 000299..000299"


def test_keep_command_writes_the_pick(tmp_path, astyx_root):
    """``msdnet-export keep`` on two Astyx frames with a tiny Astyx model."""
    from click.testing import CliRunner

    from msdnet.export.keep import main

    d = copy_artifact(make_artifact(tmp_path / "a", "student", "astyx"), tmp_path / "astyx")
    args = [str(d), "--dataset", "astyx", "--data", str(astyx_root), "--first", "000299", "--last", "000300"]
    res = CliRunner().invoke(main, [*args, "--candidates", "0.1,0.5", "--write"])
    assert res.exit_code == 0, res.output
    assert "pick:" in res.output and "| keep all |" in res.output
    art = load_artifact(d)
    assert art.keep_threshold in (0.1, 0.5)
    assert art.manifest["keep_radar_calibration"]["frames"] == ["000299", "000300"]
    bad = CliRunner().invoke(main, [*args, "--candidates", "0,0.5"])
    assert bad.exit_code != 0 and "--candidates" in bad.output
