"""Decoding thresholds by range band: the bands (``spec.range_threshold``), the Pipeline decoding
with them (equal to decoding each band at its own threshold), the manifest field, the fast scene
scorer and the choice on the selection slice (``export.bands``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from export_helpers import copy_artifact, make_artifact

from msdnet.runtime import MsdnetError, Pipeline
from msdnet.runtime.metrics.cloud import scene_scores, score_frame
from msdnet.runtime.model.artifact import load_artifact
from msdnet.runtime.spec.range_threshold import RangeThresholds, range_thresholds_from


def test_bands_of_points():
    rt = RangeThresholds((10.0, 20.0), (0.25, 0.4, 0.5))
    pts = np.array(
        [[0, 0, 0], [9.99, 0, 1], [10, 0, 0], [6, 8, 0], [12, 16, 0], [19.9, 0, 0], [40, -3, 0]], np.float32
    )
    np.testing.assert_array_equal(rt.per_point(pts), np.float32([0.25, 0.25, 0.4, 0.4, 0.5, 0.4, 0.5]))
    conf = np.float32([0.25, 0.26, 0.4, 0.41, 0.6, 0.3, 0.5])
    # the decoder's comparison: occupancy > threshold
    np.testing.assert_array_equal(rt.keep(pts, conf), [False, True, False, True, True, False, False])
    assert rt.lowest == 0.25 and rt.to_json() == {"edges_m": [10.0, 20.0], "thresholds": [0.25, 0.4, 0.5]}


@pytest.mark.parametrize(
    "edges, thresholds",
    [((10.0,), (0.3,)), ((10.0, 5.0), (0.3, 0.4, 0.5)), ((0.0,), (0.3, 0.4)), ((10.0,), (0.3, 1.0))],
)
def test_bad_bands_are_refused(edges, thresholds):
    with pytest.raises(ValueError):
        RangeThresholds(edges, thresholds)
    block = {"edges_m": list(edges), "thresholds": list(thresholds)}
    with pytest.raises(MsdnetError, match="range_thresholds"):
        range_thresholds_from(block, "m/manifest.json")


@pytest.mark.parametrize(
    "block",
    [
        [0.3],
        {"edges_m": [10]},
        {"edges_m": [10], "thresholds": ["0.3", 0.4]},
        {"edges_m": [True], "thresholds": [0.3, 0.4]},
    ],
)
def test_malformed_blocks_are_refused(block):
    with pytest.raises(MsdnetError, match="range_thresholds"):
        range_thresholds_from(block, "m/manifest.json")


def test_scene_scores_equal_the_metrics_one_by_one():
    rng = np.random.default_rng(0)
    area = (0.0, -8.0, 16.0, 8.0)
    for n_pred in (0, 1, 300):
        pred = rng.uniform((0, -8, -1), (16, 8, 2), (n_pred, 3))
        ref = rng.uniform((0, -8, -1), (16, 8, 2), (400, 3))
        fast, slow = scene_scores(pred, ref, area), score_frame(pred, ref, area)
        expect = {
            "cd": slow.cd,
            "mhd": slow.mhd,
            "fscore@0.2": slow.fscore[0.2],
            "fscore@0.5": slow.fscore[0.5],
            "jsd": slow.jsd,
        }
        assert fast.keys() == expect.keys()
        for k, v in expect.items():
            assert (np.isnan(v) and np.isnan(fast[k])) or fast[k] == v, (n_pred, k)


# ---------------------------------------------------------------- the Pipeline


def _with_bands(student_dir: Path, where: Path, block: object) -> Path:
    d = copy_artifact(student_dir, where)
    m = json.loads((d / "manifest.json").read_text())
    (d / "manifest.json").write_text(json.dumps({**m, "range_thresholds": block}))
    return d


def test_pipeline_decodes_each_band_at_its_threshold(student_dir, tmp_path, scan):
    plain = Pipeline.from_dir(student_dir, threads=1)
    x1 = plain.artifact.grid.point_range[3]
    edges = (x1 / 3, 2 * x1 / 3)
    base = plain(scan, steps=2, seed=3)
    lo, hi = np.quantile(base.confidence, [0.2, 0.6])  # thresholds that change the output
    thresholds = (float(lo), float(hi), float((lo + hi) / 2))
    d = _with_bands(student_dir, tmp_path / "bands", {"edges_m": list(edges), "thresholds": list(thresholds)})
    pipe = Pipeline.from_dir(d, threads=1)
    assert pipe.range_thresholds == RangeThresholds(edges, thresholds)
    res = pipe(scan, steps=2, seed=3)
    rt = pipe.range_thresholds
    expect = []
    for k, t in enumerate(thresholds):  # decode at each band's own threshold, keep that band's points
        one = plain(scan, steps=2, seed=3, threshold=t)
        band = np.searchsorted(edges, np.hypot(one.points[:, 0], one.points[:, 1]), side="right")
        expect.append(one.points[band == k])
    expect = np.concatenate(expect)
    assert len(expect) > 0
    np.testing.assert_array_equal(np.unique(res.points, axis=0), np.unique(expect, axis=0))
    assert np.all(rt.keep(res.points, res.confidence))
    # a threshold given explicitly is that one threshold everywhere, as without the field
    np.testing.assert_array_equal(
        pipe(scan, steps=2, seed=3, threshold=0.5).points, plain(scan, steps=2, seed=3, threshold=0.5).points
    )


def test_bad_manifest_bands_fail_in_one_line(student_dir, tmp_path):
    d = _with_bands(student_dir, tmp_path / "bad", {"edges_m": [10, 5], "thresholds": [0.3, 0.4, 0.5]})
    with pytest.raises(MsdnetError, match="range_thresholds.*increasing"):
        load_artifact(d)


def test_bands_command_writes_the_pick(tmp_path, astyx_root):
    """``msdnet-export bands`` on two Astyx frames with a tiny Astyx model."""
    from click.testing import CliRunner

    from msdnet.export.bands import main

    d = copy_artifact(make_artifact(tmp_path / "a", "student", "astyx"), tmp_path / "astyx")
    args = [str(d), "--dataset", "astyx", "--data", str(astyx_root), "--first", "000299", "--last", "000300"]
    res = CliRunner().invoke(main, [*args, "--candidates", "0.3,0.5;0.5;0.5,0.7", "--write"])
    assert res.exit_code == 0, res.output
    assert "everywhere |" in res.output
    art = load_artifact(d)
    cal = art.manifest["range_thresholds_calibration"]
    assert cal["frames"] == ["000299", "000300"] and len(cal["table"]) == 1 + 4
    if cal["thresholds"] is None:  # no combination as good as the single threshold: no field
        assert art.range_thresholds is None and "no combination" in res.output
    else:
        assert art.range_thresholds.thresholds == tuple(cal["thresholds"]) and "pick:" in res.output
    for bad, opt in (("0.3;0.5", "--candidates"), ("0,0.5;0.5;0.5", "--candidates")):
        out = CliRunner().invoke(main, [*args, "--candidates", bad])
        assert out.exit_code != 0 and opt in out.output
    out = CliRunner().invoke(main, [*args, "--edges", "20,10"])
    assert out.exit_code != 0 and "--edges" in out.output


def test_kernels_decode_each_band_at_its_threshold():
    """decode_packed / decode_sparse with bands give exactly the points of a decode at the lowest
    threshold filtered by ``RangeThresholds.keep`` (same order), and without bands what they gave."""
    from msdnet.runtime.engine.decode import decode_packed, decode_sparse, packed_shape
    from msdnet.runtime.spec.grid import GridConfig

    grid = GridConfig((0.0, -3.2, -0.6, 6.4, 3.2, 0.6), (0.2, 0.2, 0.3))  # (D, H, W) = (4, 32, 32)
    rng = np.random.default_rng(1)
    half = packed_shape(grid)
    occ = rng.random((8, *half), dtype=np.float32)
    off = rng.uniform(-0.1, 0.1, (8, 3, *half)).astype(np.float32)
    rt = RangeThresholds((2.0, 4.5), (0.3, 0.6, 0.8))
    lo_pts, lo_conf = decode_packed(occ, off, grid, rt.lowest)
    keep = rt.keep(lo_pts, lo_conf)
    assert 0 < keep.sum() < len(keep)
    pts, conf = decode_packed(occ, off, grid, 0.5, rt)
    np.testing.assert_array_equal(pts, lo_pts[keep])
    np.testing.assert_array_equal(conf, lo_conf[keep])
    # the coarse-to-fine layout: a subset of half-scale voxels, rows (N, 8)
    vox = np.sort(rng.choice(int(np.prod(half)), size=int(np.prod(half)) // 2, replace=False))
    z2, y2, x2 = np.unravel_index(vox, half)
    s_occ = occ[:, z2, y2, x2].T.copy()  # (N, 8)
    s_off = off[:, :, z2, y2, x2].transpose(2, 0, 1).copy()  # (N, 8, 3)
    s_lo, s_lo_conf = decode_sparse(s_occ, s_off, vox, grid, rt.lowest)
    s_pts, s_conf = decode_sparse(s_occ, s_off, vox, grid, 0.5, rt)
    s_keep = rt.keep(s_lo, s_lo_conf)
    np.testing.assert_array_equal(s_pts, s_lo[s_keep])
    np.testing.assert_array_equal(s_conf, s_lo_conf[s_keep])
    # one band everywhere is the single threshold
    one = RangeThresholds((100.0,), (0.5, 0.5))
    np.testing.assert_array_equal(
        decode_packed(occ, off, grid, 0.1, one)[0], decode_packed(occ, off, grid, 0.5)[0]
    )
