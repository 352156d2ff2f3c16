"""What ``msdnet-infer`` is given, checked before any scan runs: scans whose columns the model does
not read stop the run in one line naming the shipped models that read them; a whole dataset folder
is named with the ``--dataset`` that reads it; a licence or a frame list in a folder is not a scan;
the ``--png`` picture counts what it draws."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from msdnet.runtime.frontends.infer.cli import main
from msdnet.runtime.frontends.infer.scans import dataset_layout, is_scan, shipped_models_for
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL
from msdnet.runtime.io.pictures import read_counts

MODELS = BUNDLED_MODEL.parent
ASTYX_MODELS = ["astyx-lite", "astyx-lite-nodgfd", "astyx-lite-r2ldm"]


def _infer(args: list) -> object:
    return CliRunner().invoke(main, [str(a) for a in args])


def _error_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.strip()]


def _suggested(line: str) -> str:
    """The model an error line tells the user to pass with --model (a shipped model's name)."""
    match = re.search(r"use --model (\S+),", line)
    assert match, line
    return match.group(1)


def test_astyx_scans_with_the_default_model_stop_in_one_line(astyx_root, tmp_path):
    r = _infer([astyx_root / "radar_6455", "--out", tmp_path / "x"])
    assert r.exit_code == 2, r.output
    (line,) = _error_lines(r.output)  # one line for the run, not one per scan
    assert line.startswith("error: ") and "FAILED" not in line and "Traceback" not in line
    assert "(440 .txt scans)" in line and "rcs, v_r_compensated missing" in line
    assert _suggested(line) == "astyx-lite"
    assert not (tmp_path / "x").exists()  # stopped before any work


def test_dataset_mode_with_the_wrong_model_stops_in_one_line(astyx_root, tmp_path):
    r = _infer([astyx_root, "--dataset", "astyx", "--frames", "1", "--out", tmp_path / "x"])
    assert r.exit_code == 2, r.output
    (line,) = _error_lines(r.output)
    assert "the model" in line and _suggested(line) == "astyx-lite"


def test_a_fitting_model_is_not_refused(astyx_root, tmp_path):
    scan = astyx_root / "radar_6455" / "000001.txt"
    r = _infer([scan, "--model", MODELS / "astyx-lite", "--provider", "cpu", "--out", tmp_path])
    assert r.exit_code == 0, r.output
    assert "files: 1 ok, 0 failed" in r.output


def test_shipped_models_for_columns():
    assert [p.name for p in shipped_models_for(("x", "y", "z", "v_r", "mag"), MODELS)] == ASTYX_MODELS
    vod = ("x", "y", "z", "rcs", "v_r", "v_r_compensated", "time")
    assert [p.name for p in shipped_models_for(vod, MODELS)] == ["sim-lite", "sim-lite-r2ldm"]
    assert shipped_models_for(("x", "y", "z"), MODELS) == []


def test_no_fitting_model_says_so(tmp_path):
    scan = tmp_path / "scan.txt"
    scan.write_text("x y z intensity\n1 2 0.5 3\n4 5 0.5 6\n")
    r = _infer([scan, "--out", tmp_path / "out"])
    assert r.exit_code == 2, r.output
    (line,) = _error_lines(r.output)
    assert "no shipped model reads them" in line


@pytest.mark.parametrize(
    ("root", "key"),
    [("astyx", "astyx"), ("vod", "vod")],
)
def test_a_dataset_root_names_its_dataset_option(astyx_root, vod_root, tmp_path, root, key):
    folder = astyx_root if root == "astyx" else vod_root
    r = _infer([folder, "--out", tmp_path / "x"])
    assert r.exit_code == 2, r.output
    (line,) = _error_lines(r.output)
    assert f"add --dataset {key}" in line and "LICENSE" not in line


def test_simulator_output_is_recognised(tmp_path):
    sim = tmp_path / "sim"
    for side in ("radar", "lidar"):
        (sim / side / "training" / "velodyne").mkdir(parents=True)
    (sim / "sequences.json").write_text(json.dumps({"sequences": []}))
    assert dataset_layout(sim)[0] == "sim"
    (sim / "sequences.json").write_text(json.dumps({"sequences": [], "rig": "astyx"}))
    assert dataset_layout(sim)[0] == "sim-astyx"
    assert dataset_layout(sim / "radar") is None
    r = _infer([sim, "--out", tmp_path / "x"])
    assert r.exit_code == 2 and "add --dataset sim-astyx" in r.output


def test_files_that_are_not_scans_are_left_out(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    texts = {
        "LICENSE.txt": "Copyright (c) 2019 Astyx GmbH\n",
        "train.txt": "00001\n00002\n",
        "calib.txt": "P0: 1 0 0 0 0 1 0 0 0 0 1 0\n",
        "label.txt": "Car 0 0 -10 1 2 3 4 1.5 1.6 4.0 1 2 3 0.1\n",
        "scan.txt": "\nX Y Z V_r Mag\n1 2 0 0.5 40\n",
        "lower.txt": "x y z v_r mag\n1 2 0 0.5 40\n3 4 0 0.5 41\n",
    }
    for name, text in texts.items():
        (folder / name).write_text(text)
    scans = sorted(p.name for p in folder.iterdir() if is_scan(p))
    assert scans == ["lower.txt", "scan.txt"]
    (tmp_path / "bare.txt").write_text("1 2 0 0.5 40\n3 4 0 0.5 41\n")  # no header: rows of numbers
    assert is_scan(tmp_path / "bare.txt") and is_scan(tmp_path / "x.bin")
    r = _infer(
        [folder, "--model", BUNDLED_MODEL.parent / "astyx-lite", "--provider", "cpu", "--out", tmp_path / "o"]
    )
    assert "files: 2 ok, 0 failed" in r.output, r.output


def test_png_counts_the_points_drawn(astyx_root, tmp_path):
    scan = astyx_root / "radar_6455" / "000395.txt"
    r = _infer([scan, "--model", MODELS / "astyx-lite", "--provider", "cpu", "--out", tmp_path, "--png"])
    assert r.exit_code == 0, r.output
    out = np.load(tmp_path / "000395.npy")
    counts = read_counts(tmp_path / "000395.png")
    assert counts["MSDNet output"] == len(out)
    assert "points in 2296 (dropped 1476 outside the grid)" in r.output
    assert counts["radar in the grid"] == 2296 - 1476  # the radar outside the grid is not drawn


def test_read_counts_of_a_picture_without_them(tmp_path):
    from matplotlib.figure import Figure

    fig = Figure()
    fig.savefig(tmp_path / "plain.png")
    assert read_counts(tmp_path / "plain.png") == {}
    assert isinstance(Path(tmp_path / "plain.png").read_bytes(), bytes)
