"""Threshold calibration on training frames: the table is what decoding gives, the choice is its
lowest Chamfer distance, and ``msdnet-export --calibrate`` writes it into the manifest."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner
from export_helpers import make_checkpoint, one_torch_thread

from msdnet.export.cli import main as export_main
from msdnet.training.recipe.calibrate import CANDIDATES, calibrate_threshold, pick_frames
from msdnet.training.recipe.checkpoint import load_checkpoint


def test_pick_frames_spread_and_bounded():
    assert pick_frames(10, 3) == [0, 4, 9]
    assert pick_frames(2, 5) == [0, 1]


def test_calibration_table_and_choice(tmp_path, vod_root):
    model, cfg, _ = load_checkpoint(make_checkpoint(tmp_path / "s", "student", "vod"))
    with one_torch_thread():
        best, rows = calibrate_threshold(model, cfg, "vod", str(vod_root), frames=2)
    assert [r.threshold for r in rows] == list(CANDIDATES)
    points = [r.points for r in rows]
    assert all(a >= b for a, b in zip(points, points[1:], strict=False))  # higher threshold, fewer points
    assert points[0] > points[-1]
    usable = [r for r in rows if r.empty == 0]
    assert best == min(usable, key=lambda r: (r.rank, r.cd)).threshold
    assert all(1.0 <= r.rank <= len(CANDIDATES) for r in rows)
    assert all(np.isfinite(r.cd) and r.cd > 0 for r in usable)


def test_export_calibrate_writes_the_threshold(tmp_path, vod_root):
    ckpt = make_checkpoint(tmp_path / "s", "student", "vod")
    args = [ckpt, "--out", tmp_path / "m", "--calibrate", "2", "--data", vod_root, "--dataset", "vod"]
    r = CliRunner().invoke(export_main, [str(a) for a in [*args, "--threads", "1"]])
    assert r.exit_code == 0, r.output
    chosen = [line for line in r.output.splitlines() if line.endswith("<- chosen")]
    assert len(chosen) == 1
    m = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert m["threshold"] == float(chosen[0].split()[0])
    r = CliRunner().invoke(export_main, [str(a) for a in [ckpt, "--out", tmp_path / "n", "--calibrate", "2"]])
    assert r.exit_code == 2 and "needs --data and --dataset" in r.output
