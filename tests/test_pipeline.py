"""The runtime Pipeline: Python API, determinism, run-time step counts, the IOBinding loop against
a plain loop, empty scans, column handling, R2LDM artifacts, and every artifact check."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from export_helpers import copy_artifact, make_artifact

from msdnet.runtime import MsdnetError, Pipeline, PointCloud
from msdnet.runtime.engine.decode import decode_packed
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import load_artifact

STAGES = {"prepare", "voxelize", "encoder", "adapter", "denoise", "head", "decode", "total"}


@pytest.fixture(scope="module")
def pipe(student_dir) -> Pipeline:
    return Pipeline.from_dir(student_dir, threads=1)


def test_api_on_a_real_scan(pipe, scan):
    res = pipe(scan, steps=4)
    assert res.points.dtype == np.float32 and res.points.shape[1] == 3
    assert res.confidence.shape == (len(res.points),) and len(res.points) > 1000
    assert np.all(res.confidence > pipe.artifact.threshold)
    assert set(res.timings) == STAGES and res.timings["total"] > 0
    assert res.stats["points_in"] == 322 and 0 < res.stats["voxels"] <= res.stats["points_in_grid"]
    lo, hi = np.array(pipe.artifact.grid.point_range[:3]), np.array(pipe.artifact.grid.point_range[3:])
    assert np.all(res.points >= lo) and np.all(res.points <= hi)
    # an array in the manifest's column order gives the same output as the PointCloud
    arr = scan.select(pipe.columns).points
    np.testing.assert_array_equal(pipe(arr, steps=4).points, res.points)


def test_same_seed_bit_identical(pipe, scan):
    a, b = pipe(scan, seed=7), pipe(scan, seed=7)
    assert a.points.tobytes() == b.points.tobytes()
    assert a.confidence.tobytes() == b.confidence.tobytes()
    c = pipe(scan, seed=8)
    assert c.points.shape != a.points.shape or not np.array_equal(c.points, a.points)


def _plain_loop(pipe: Pipeline, pts: np.ndarray, steps: int, seed: int) -> np.ndarray:
    """Reference without IOBinding: session.run with numpy feeds, fresh arrays every step."""
    from msdnet.runtime.engine.rulebook import batch_coords, build_encoder_rulebooks
    from msdnet.runtime.engine.voxelize import voxelize

    art = pipe.artifact
    vox = voxelize(pts, art.grid, art.inputs.max_voxels)
    rb = build_encoder_rulebooks(batch_coords([vox.coords]), art.grid.shape_zyx)
    feeds = {"voxel_features": vox.features, "subm_rules_0": rb.subm[0].astype(np.int64)}
    for lvl in (1, 2, 3):
        feeds[f"down_rules_{lvl}"] = rb.down[lvl - 1].astype(np.int64)
        feeds[f"subm_rules_{lvl}"] = rb.subm[lvl].astype(np.int64)
    feeds["bev_coords"] = rb.coords[3].astype(np.int64)
    (f_s,) = pipe.sessions["encoder.onnx"].run(None, feeds)
    noise = np.random.default_rng(seed).standard_normal(f_s.shape, dtype=np.float32)
    (x,) = pipe.sessions["rgfd_adapter.onnx"].run(None, {"bev_features": f_s, "noise": noise})
    for t, a, ap in pipe.coefficients(steps):
        f = {"x_t": x, "t": np.array([t]), "abar_t": np.array([a]), "abar_prev": np.array([ap])}
        (x,) = pipe.sessions["denoiser_step.onnx"].run(None, f)
    occ, off = pipe.sessions["recon_head.onnx"].run(None, {"features": x})
    return decode_packed(occ[0], off[0], art.grid, art.threshold)[0]


@pytest.mark.parametrize("steps", [1, 4, 7])
def test_step_count_at_run_time_matches_plain_loop(pipe, scan, steps):
    """Any step count runs without re-export; the ping-pong IOBinding loop (odd and even counts)
    gives exactly what a plain session.run loop gives."""
    res = pipe(scan, steps=steps, seed=3)
    assert res.stats["steps"] == steps
    ref = _plain_loop(pipe, scan.select(pipe.columns).points, steps, seed=3)
    np.testing.assert_array_equal(res.points, ref)


def test_bad_steps_and_threshold(pipe, scan):
    with pytest.raises(MsdnetError, match="steps"):
        pipe(scan, steps=501)  # more than m
    with pytest.raises(MsdnetError, match="threshold"):
        pipe(scan, threshold=1.5)
    assert len(pipe(scan, steps=2, threshold=0.9).points) < len(pipe(scan, steps=2).points)


def test_empty_scans(pipe):
    c = len(pipe.columns)
    none = pipe(np.zeros((0, c), np.float32))
    assert none.points.shape == (0, 3) and none.confidence.shape == (0,)
    assert "empty scan" in none.notes[0]
    outside = np.full((5, c), 100.0, np.float32)  # every point beyond the grid
    res = pipe(outside)
    assert len(res.points) == 0 and "no point inside the grid" in res.notes[0]


def _radar_in_grid(pipe: Pipeline, arr: np.ndarray) -> np.ndarray:
    """(K, 3) float32 xyz of the rows the voxelizer keeps: finite, lo <= p < hi in float64."""
    lo = np.asarray(pipe.artifact.grid.point_range[:3], np.float64)
    hi = np.asarray(pipe.artifact.grid.point_range[3:], np.float64)
    xyz = arr[:, :3].astype(np.float64)
    keep = np.isfinite(arr).all(axis=1) & (xyz >= lo).all(axis=1) & (xyz < hi).all(axis=1)
    return arr[keep, :3]


def test_keep_radar_appends_the_radar_in_the_grid(pipe, scan):
    """keep_radar: model points first (exactly the output without it), then the radar rows inside
    the grid box in input order, confidence 1; rows outside the box or non-finite are left out."""
    arr = scan.select(pipe.columns).points
    extra = np.zeros((3, arr.shape[1]), np.float32)
    extra[0, :3] = 1000.0  # far outside the grid
    extra[1, :3] = arr[0, :3]
    extra[1, 3] = np.nan  # inside the box but non-finite: the voxelizer drops it
    extra[2, :3] = pipe.artifact.grid.point_range[3:]  # on the upper faces: half-open box, out
    arr = np.concatenate([arr[:100], extra, arr[100:]])
    base = pipe(arr, steps=3, seed=5)
    res = pipe(arr, steps=3, seed=5, keep_radar=True)
    radar = _radar_in_grid(pipe, arr)
    m, k = len(base.points), len(radar)
    assert m > 1000 and 0 < k == res.stats["points_in_grid"] == res.stats["radar_kept"] < len(arr) - 3
    assert res.points.shape == (m + k, 3) and res.confidence.shape == (m + k,)
    assert res.points.dtype == np.float32 and res.confidence.dtype == np.float32
    assert res.points.flags.c_contiguous
    np.testing.assert_array_equal(res.points[:m], base.points)
    np.testing.assert_array_equal(res.confidence[:m], base.confidence)
    np.testing.assert_array_equal(res.points[m:], radar)
    assert np.all(res.confidence[m:] == 1.0)
    assert "radar_kept" not in base.stats
    # a PointCloud gives the same as the array in manifest column order
    again = pipe(scan, steps=3, seed=5, keep_radar=True)
    plain = pipe(scan, steps=3, seed=5)
    np.testing.assert_array_equal(
        again.points[len(plain.points) :], _radar_in_grid(pipe, scan.select(pipe.columns).points)
    )


def test_keep_radar_edge_cases(pipe, scan):
    c = len(pipe.columns)
    outside = pipe(np.full((5, c), 100.0, np.float32), keep_radar=True)
    assert outside.points.shape == (0, 3) and outside.confidence.shape == (0,)
    # no voxel above the threshold: the output is the radar points alone, and the note says so
    res = pipe(scan, steps=1, threshold=0.999999, keep_radar=True)
    radar = _radar_in_grid(pipe, scan.select(pipe.columns).points)
    np.testing.assert_array_equal(res.points, radar)
    assert "radar points only" in res.notes[0]


def test_columns(pipe, scan):
    assert pipe.columns == ("x", "y", "z", "rcs", "v_r_compensated")
    with pytest.raises(MsdnetError, match=r"must be \(N, 5\)"):
        pipe(scan.points)  # 7 VoD columns, not the manifest's 5
    astyx_like = PointCloud(scan.points[:, :5], ("x", "y", "z", "v_r", "mag"))
    with pytest.raises(MsdnetError, match="no column 'rcs'"):
        pipe(astyx_like)


def test_r2ldm_pipeline(tmp_path_factory, scan):
    d = make_artifact(tmp_path_factory.mktemp("r2"), "r2ldm")
    p = Pipeline.from_dir(d, threads=1)
    assert p.kind == "r2ldm" and set(p.sessions) == {
        s.file for s in (*onnx_spec.R2LDM_GRAPHS, *onnx_spec.OPTIONAL_GRAPHS)
    }
    a, b = p(scan, steps=3, seed=1), p(scan, steps=3, seed=1)
    assert len(a.points) > 0 and a.points.tobytes() == b.points.tobytes()
    assert p(scan, steps=2, seed=1).stats["steps"] == 2


def test_unknown_provider(student_dir):
    with pytest.raises(MsdnetError, match=r"'cuda' is not available .*available: cpu"):
        Pipeline.from_dir(student_dir, provider="cuda")


# ---------------------------------------------------------------- artifact checks


def _tamper(folder: Path, file: str) -> None:
    data = bytearray((folder / file).read_bytes())
    data[len(data) // 2] ^= 0x01
    (folder / file).write_bytes(bytes(data))


@pytest.mark.parametrize("graph", [s.file for s in onnx_spec.MSDNET_GRAPHS])
def test_one_flipped_byte_is_refused(student_dir, tmp_path, graph):
    d = copy_artifact(student_dir, tmp_path / "a")
    _tamper(d, graph)
    with pytest.raises(MsdnetError, match=rf"^{graph}: sha256 mismatch \(manifest [0-9a-f]+"):
        load_artifact(d)


def _edit_manifest(folder: Path, **changes) -> None:
    m = json.loads((folder / "manifest.json").read_text())
    m.update(changes)
    (folder / "manifest.json").write_text(json.dumps(m))


def test_artifact_refusals(student_dir, tmp_path):
    d = copy_artifact(student_dir, tmp_path / "missing")
    (d / "recon_head.onnx").unlink()
    with pytest.raises(MsdnetError, match=r"recon_head.onnx: graph file is missing"):
        load_artifact(d)

    d = copy_artifact(student_dir, tmp_path / "version")
    _edit_manifest(d, format_version=99)
    with pytest.raises(MsdnetError, match="format version 99 is not supported"):
        load_artifact(d)

    d = copy_artifact(student_dir, tmp_path / "size")
    with open(d / "encoder.onnx", "ab") as f:
        f.write(b"\0")
    with pytest.raises(MsdnetError, match=r"encoder.onnx: size mismatch"):
        load_artifact(d)

    d = copy_artifact(student_dir, tmp_path / "link")
    target = tmp_path / "elsewhere.onnx"
    os.replace(d / "denoiser_step.onnx", target)
    (d / "denoiser_step.onnx").symlink_to(target)
    with pytest.raises(MsdnetError, match="symlink"):
        load_artifact(d)

    d = copy_artifact(student_dir, tmp_path / "escape")
    m = json.loads((d / "manifest.json").read_text())
    m["graphs"][0]["file"] = "../encoder.onnx"
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(MsdnetError, match="graph list does not match"):
        load_artifact(d)

    d = copy_artifact(student_dir, tmp_path / "json")
    (d / "manifest.json").write_text("{not json")
    with pytest.raises(MsdnetError, match="not valid JSON"):
        load_artifact(d)

    with pytest.raises(MsdnetError, match="model folder not found"):
        load_artifact(tmp_path / "nothing")


def test_external_data_graph_refused(student_dir, tmp_path):
    """A graph re-saved with its weights in a side file is refused even with a matching hash."""
    import onnx

    from msdnet.runtime.model.artifact import file_digest

    d = copy_artifact(student_dir, tmp_path / "ext")
    model = onnx.load(d / "denoiser_step.onnx")
    onnx.save_model(model, d / "denoiser_step.onnx", save_as_external_data=True, location="w.bin")
    m = json.loads((d / "manifest.json").read_text())
    for g in m["graphs"]:
        g["bytes"], g["sha256"] = file_digest(d / g["file"])
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(MsdnetError, match="denoiser_step.onnx: keeps tensors in external files"):
        load_artifact(d)
