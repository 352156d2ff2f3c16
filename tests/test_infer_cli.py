"""``msdnet-infer`` on real VoD and Astyx radar scans: every output format reads back equal to
the Pipeline's output, bad files do not stop a batch, tampered models and bad arguments are
refused with one line."""

from __future__ import annotations

import dataclasses
import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from export_helpers import copy_artifact, make_artifact

from msdnet.runtime import Pipeline, read_cloud
from msdnet.runtime.frontends import model_args
from msdnet.runtime.frontends.densify import DensifyOptions, densify
from msdnet.runtime.frontends.infer.cli import OUT_COLUMNS, main
from msdnet.runtime.model import onnx_spec

STEPS = ["--steps", "3", "--threads", "1"]


@pytest.fixture(scope="module")
def vod_model(tmp_path_factory) -> Path:
    return make_artifact(tmp_path_factory.mktemp("art"), "student", "vod")


@pytest.fixture(scope="module")
def vod_scans(vod_root) -> list[Path]:
    return sorted((vod_root / "radar" / "training" / "velodyne").glob("*.bin"))


def _infer(args: list) -> object:
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


def _expected(model: Path, scan: Path) -> np.ndarray:
    """(M, 4) [x, y, z, confidence] straight from the Python API."""
    res = Pipeline.from_dir(model, threads=1)(read_cloud(scan), steps=3)
    return np.concatenate([res.points, res.confidence[:, None]], axis=1)


@pytest.mark.parametrize("fmt", ["npy", "bin", "pcd", "ply"])
def test_vod_folder_every_format_reads_back(vod_model, vod_scans, vod_root, tmp_path, fmt):
    folder = vod_root / "radar" / "training" / "velodyne"
    r = _infer([folder, "--model", vod_model, "--out", tmp_path, "--format", fmt, *STEPS])
    assert r.exit_code == 0, r.output
    assert f"files: {len(vod_scans)} ok, 0 failed" in r.output
    for scan in vod_scans:
        out = tmp_path / f"{scan.stem}.{fmt}"
        cols = OUT_COLUMNS if fmt in ("npy", "bin") else None
        back = read_cloud(out, columns=cols)
        assert back.columns == OUT_COLUMNS
        np.testing.assert_array_equal(back.points, _expected(vod_model, scan))
    assert not list(tmp_path.glob(".*tmp"))


def test_astyx_scans_and_png(tmp_path_factory, astyx_root, tmp_path):
    model = make_artifact(tmp_path_factory.mktemp("art"), "student", "astyx")
    scans = [astyx_root / "radar_6455" / f"{i:06d}.txt" for i in (0, 1)]
    r = _infer([*scans, "--model", model, "--out", tmp_path, "--png", *STEPS])
    assert r.exit_code == 0, r.output
    assert "points in 1" in r.output  # frame 000000 alone has 831 detections
    for scan in scans:
        back = read_cloud(tmp_path / f"{scan.stem}.npy", columns=OUT_COLUMNS)
        np.testing.assert_array_equal(back.points, _expected(model, scan))
        assert (tmp_path / f"{scan.stem}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_file_does_not_stop_the_batch(vod_model, vod_scans, tmp_path):
    inputs = tmp_path / "in"
    inputs.mkdir()
    (inputs / "broken.npy").write_bytes(b"not a numpy file")
    (inputs / "short.txt").write_text("x y z rcs v_r_compensated\n1 2 3 4\n")  # a row a value short
    out = tmp_path / "out"
    r = _infer(
        [
            inputs / "broken.npy",
            vod_scans[0],
            inputs / "short.txt",
            "--model",
            vod_model,
            "--out",
            out,
            *STEPS,
        ]
    )
    assert r.exit_code == 1, r.output
    assert "files: 1 ok, 2 failed" in r.output
    assert "FAILED " + str(inputs / "broken.npy") in r.output
    assert "FAILED " + str(inputs / "short.txt") in r.output
    assert (out / f"{vod_scans[0].stem}.npy").is_file()


def test_output_equal_to_input_is_refused(vod_model, vod_scans, tmp_path):
    src = tmp_path / "scan.npy"
    np.save(src, read_cloud(vod_scans[0]).select(("x", "y", "z", "rcs", "v_r_compensated")).points)
    r = _infer([src, "--model", vod_model, "--out", tmp_path, "--format", "npy"])
    assert r.exit_code == 2 and f"--out is the folder of input {src}" in r.output


def test_same_seed_bit_identical_files_and_workers(vod_model, vod_scans, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert _infer([*vod_scans[:2], "--model", vod_model, "--out", a, *STEPS]).exit_code == 0
    r = _infer([*vod_scans[:2], "--model", vod_model, "--out", b, "--workers", "2", *STEPS])
    assert r.exit_code == 0, r.output
    for scan in vod_scans[:2]:
        assert (a / f"{scan.stem}.npy").read_bytes() == (b / f"{scan.stem}.npy").read_bytes()


@pytest.mark.parametrize("workers", ["1", "2"])
def test_keep_radar_flag_appends_radar_rows(vod_model, vod_scans, tmp_path, workers):
    """--keep-radar (also through --workers processes): each file is the default output followed
    by the scan's radar points inside the grid box, confidence 1."""
    scans = vod_scans[:2]
    a, b = tmp_path / "a", tmp_path / "b"
    assert _infer([*scans, "--model", vod_model, "--out", a, *STEPS]).exit_code == 0
    r = _infer([*scans, "--model", vod_model, "--out", b, "--keep-radar", "--workers", workers, *STEPS])
    assert r.exit_code == 0, r.output
    pipe = Pipeline.from_dir(vod_model, threads=1)
    lo, hi = np.array(pipe.artifact.grid.point_range[:3]), np.array(pipe.artifact.grid.point_range[3:])
    for scan in scans:
        plain = read_cloud(a / f"{scan.stem}.npy", columns=OUT_COLUMNS).points
        kept = read_cloud(b / f"{scan.stem}.npy", columns=OUT_COLUMNS).points
        xyz = read_cloud(scan).xyz
        radar = xyz[np.all((xyz >= lo) & (xyz < hi), axis=1)]
        assert len(radar) > 0 and kept.shape == (len(plain) + len(radar), 4)
        np.testing.assert_array_equal(kept[: len(plain)], plain)
        np.testing.assert_array_equal(kept[len(plain) :, :3], radar)
        assert np.all(kept[len(plain) :, 3] == 1.0)


@pytest.mark.parametrize("graph", [s.file for s in onnx_spec.MSDNET_GRAPHS])
def test_tampered_graph_refused_by_name(vod_model, vod_scans, tmp_path, graph):
    model = copy_artifact(vod_model, tmp_path / "model")
    data = bytearray((model / graph).read_bytes())
    data[-100] ^= 0xFF
    (model / graph).write_bytes(bytes(data))
    r = _infer([vod_scans[0], "--model", model, "--out", tmp_path / "out"])
    assert r.exit_code == 2
    assert r.output.startswith(f"error: {graph}: sha256 mismatch (manifest ")
    assert len(r.output.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_missing_graph_and_wrong_version(vod_model, vod_scans, tmp_path):
    model = copy_artifact(vod_model, tmp_path / "m1")
    (model / "rgfd_adapter.onnx").unlink()
    r = _infer([vod_scans[0], "--model", model, "--out", tmp_path / "o"])
    assert r.exit_code == 2 and "rgfd_adapter.onnx: graph file is missing" in r.output
    model = copy_artifact(vod_model, tmp_path / "m2")
    manifest = json.loads((model / "manifest.json").read_text())
    manifest["format_version"] = onnx_spec.FORMAT_VERSION + 1
    (model / "manifest.json").write_text(json.dumps(manifest))
    r = _infer([vod_scans[0], "--model", model, "--out", tmp_path / "o"])
    assert r.exit_code == 2 and "is not supported" in r.output


def test_no_model_and_none_bundled(vod_scans, tmp_path, monkeypatch):
    monkeypatch.setattr(model_args, "BUNDLED_MODEL", tmp_path / "nowhere")
    r = _infer([vod_scans[0], "--out", tmp_path / "o"])
    assert r.exit_code == 2 and "no model given and no bundled model" in r.output


def test_console_script_one_line_error(vod_model, vod_scans, tmp_path):
    """The installed entry point: a bad provider is one line on stderr, exit 2, no traceback."""
    exe = Path(sys.executable).with_name("msdnet-infer")
    cmd = [str(exe), str(vod_scans[0]), "--model", str(vod_model), "--out", str(tmp_path)]
    r = subprocess.run([*cmd, "--provider", "tensorrt"], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("error: provider: 'tensorrt' is not available")
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_densify_options_are_frozen_picklable_and_reach_the_pipeline(vod_model, vod_scans):
    """The one options object every mode builds travels to worker processes and Ray actors as a
    pickle, cannot be changed on the way, and gives densify the same result as the keywords."""
    options = DensifyOptions(steps=2, seed=3, keep_radar=True, fmt="ply", bin_columns=("x", "y", "z"))
    assert pickle.loads(pickle.dumps(options)) == options
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.seed = 4  # type: ignore[misc]
    pipe = Pipeline.from_dir(vod_model, threads=1)
    cloud = read_cloud(vod_scans[0])
    res = densify(pipe, cloud, options)
    ref = pipe(cloud, steps=2, threshold=None, seed=3, keep_radar=True)
    assert np.array_equal(res.points, ref.points) and np.array_equal(res.confidence, ref.confidence)
