"""Inputs by layout: a folder of VoD radar ``.bin`` scans under any name densifies whole."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.infer.cli import main
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL
from msdnet.runtime.io.files import read_cloud
from msdnet.runtime.io.layouts import LAYOUTS, layout_for_columns, resolve_bin_columns

IDS = ("00549", "01047", "01201")


def _infer(*args: object):
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


@pytest.fixture(scope="module")
def scans(vod_root: Path, tmp_path_factory) -> Path:
    """The three VoD example radar scans in a folder whose name says nothing about them."""
    folder = tmp_path_factory.mktemp("my_drive") / "scans"
    folder.mkdir()
    for fid in IDS:
        shutil.copy(vod_root / "radar" / "training" / "velodyne" / f"{fid}.bin", folder / f"{fid}.bin")
    return folder


def test_vod_scans_under_any_name_all_densify(scans: Path, vod_root: Path, tmp_path: Path) -> None:
    assert (scans / "01047.bin").stat().st_size % 112 == 0  # ambiguous by size: 7 or 4 float32
    r = _infer(scans, "--out", tmp_path / "dense")
    assert r.exit_code == 0, r.output
    assert "3 ok, 0 failed" in r.output
    ref = tmp_path / "ref"  # the same scans read from the devkit's radar/ folder
    r = _infer(*(vod_root / "radar" / "training" / "velodyne" / f"{i}.bin" for i in IDS), "--out", ref)
    assert r.exit_code == 0, r.output
    for fid in IDS:
        assert np.array_equal(np.load(tmp_path / "dense" / f"{fid}.npy"), np.load(ref / f"{fid}.npy"))


def test_older_manifest_keeps_the_path_or_size_rule(scans: Path, tmp_path: Path) -> None:
    model = tmp_path / "old-model"
    shutil.copytree(BUNDLED_MODEL, model)
    manifest = json.loads((model / "manifest.json").read_text())
    del manifest["input"]["layout"]
    (model / "manifest.json").write_text(json.dumps(manifest, indent=1))
    r = _infer(scans, "--out", tmp_path / "a", "--model", model)
    assert r.exit_code == 1 and "01047.bin" in r.output and "cannot tell VoD radar" in r.output
    r = _infer(scans, "--out", tmp_path / "b", "--model", model, "--layout", "vod-radar")
    assert r.exit_code == 0 and "3 ok" in r.output, r.output
    r = _infer(
        scans, "--out", tmp_path / "c", "--model", model, "--columns", "x,y,z,rcs,v_r,v_r_compensated,time"
    )
    assert r.exit_code == 0 and "3 ok" in r.output, r.output


def test_wrong_layout_is_one_line_per_file(scans: Path, tmp_path: Path) -> None:
    r = _infer(scans, "--out", tmp_path / "o", "--layout", "astyx-radar")  # 5 columns: no rcs
    assert r.exit_code == 1 and r.output.count("FAILED") == 3 and "Traceback" not in r.output
    r = _infer(scans, "--out", tmp_path / "p", "--layout", "xyz", "--columns", "x,y,z")
    assert r.exit_code == 2 and "give one of them" in r.output


def test_layout_rules() -> None:
    assert layout_for_columns(("x", "y", "z", "rcs", "v_r_compensated")) == "vod-radar"
    assert layout_for_columns(("x", "y", "z", "v_r", "mag")) == "astyx-radar"
    assert layout_for_columns(("x", "y", "z", "doppler")) is None
    for name in ("sim-lite", "astyx-lite"):
        manifest = json.loads((BUNDLED_MODEL.parent / name / "manifest.json").read_text())
        assert manifest["input"]["layout"] == layout_for_columns(manifest["input"]["columns"])
    assert resolve_bin_columns(None, None, {"input": {}})[0] is None
    assert resolve_bin_columns("kitti-lidar", None, {})[0] == LAYOUTS["kitti-lidar"]
    with pytest.raises(MsdnetError, match="must start with x,y,z"):
        resolve_bin_columns(None, "rcs,x,y,z", {})


def test_layout_reads_kitti_lidar_columns(vod_root: Path) -> None:
    path = vod_root / "lidar" / "training" / "velodyne" / "00549.bin"
    cloud = read_cloud(path, columns=LAYOUTS["kitti-lidar"])
    assert cloud.columns == ("x", "y", "z", "intensity") and len(cloud) == path.stat().st_size // 16
