"""``msdnet-bench steps``: Table III on a dataset split, scored exactly as ``msdnet-bench quality``."""

from __future__ import annotations

import json
import math

import pytest
from click.testing import CliRunner
from export_helpers import make_artifact

from msdnet.benchmarks.cli import main
from msdnet.benchmarks.latency.steps import fewest_close_steps, relative_pct


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return make_artifact(tmp_path_factory.mktemp("steps"), "student")


def test_sweep_matches_the_quality_command(folder, vod_root, tmp_path):
    common = ["--model", str(folder), "--dataset", "vod", "--data", str(vod_root), "--split", "all"]
    common += ["--max-frames", "2", "--threads", "1"]
    out = tmp_path / "steps"
    res = CliRunner().invoke(main, ["steps", *common, "--steps", "3,1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "results.json").read_text())
    rows = doc["rows"]
    assert [r["steps"] for r in rows] == [1, 3] and doc["evaluation"]["frames"] == 2
    for r in rows:
        assert r["frames"] == 2 and r["points"] > 0 and r["ms"] >= r["loop_ms"] > 0
        assert 0 < r["cd"] < 20 and 0 <= r["fscore@0.5"] <= 1 and 0 <= r["jsd"] <= 1
    assert all(v == 0 for v in rows[-1]["vs_last_pct"].values())
    assert doc["command"].startswith("msdnet-bench steps --model") and "--steps 3,1" in doc["command"]
    md = (out / "results.md").read_text()
    assert "| T_m | CD m | Δ CD |" in md and "| 3 | " in md and "shared with other work" in md
    q = tmp_path / "quality"
    res = CliRunner().invoke(main, ["quality", *common, "--steps", "3", "--pictures", "0", "--out", str(q)])
    assert res.exit_code == 0, res.output
    summary = json.loads((q / "results.json").read_text())["summary"]
    ours = [v for k, v in summary.items() if "onnxruntime" in k]
    assert len(ours) == 1
    for key in ("cd", "mhd", "fscore@0.5", "jsd", "points"):
        assert math.isclose(ours[0][key], rows[-1][key], rel_tol=1e-9), key


def test_bad_arguments_give_one_line(folder, vod_root, tmp_path):
    args = [
        "steps",
        "--model",
        str(folder),
        "--dataset",
        "vod",
        "--data",
        str(vod_root),
        "--out",
        str(tmp_path),
    ]
    res = CliRunner().invoke(main, [*args, "--split", "all", "--steps", "1,x"])
    assert res.exit_code == 2 and "--steps" in res.output and len(res.output.strip().splitlines()) == 1
    r2 = make_artifact(tmp_path, "r2ldm")
    rest = ["--dataset", "vod", "--data", str(vod_root), "--out", str(tmp_path), "--split", "all"]
    res = CliRunner().invoke(main, ["steps", "--model", str(r2), *rest])
    assert res.exit_code == 2 and "r2ldm" in res.output and len(res.output.strip().splitlines()) == 1


def test_relative_figures_and_the_fewest_steps():
    assert relative_pct(1.01, 1.0) == pytest.approx(1.0) and math.isnan(relative_pct(1.0, 0.0))
    rows = [
        {"steps": 1, "vs_last_pct": {"cd": 3.0, "fscore@0.5": 0.0}},
        {"steps": 4, "vs_last_pct": {"cd": 0.5, "fscore@0.5": -0.9}},
        {"steps": 50, "vs_last_pct": {"cd": 0.0, "fscore@0.5": 0.0}},
    ]
    assert fewest_close_steps(rows) == 4
    rows[1]["vs_last_pct"]["fscore@0.5"] = -1.5
    assert fewest_close_steps(rows) == 50


def test_select_split_scores_the_runs_held_out_slice(folder, vod_root, tmp_path):
    """``--split select``: the frames of the training run's selection slice (where T_m is chosen),
    read from ``--checkpoint``; without one, from the manifest's source, which must exist."""
    from export_helpers import tiny_config

    from msdnet.runtime.io.datasets import open_dataset
    from msdnet.training.config import TrainConfig
    from msdnet.training.models.assembly import build_model
    from msdnet.training.recipe.checkpoint import CheckpointState, save_checkpoint

    ids = list(open_dataset("vod", vod_root, None).frame_ids)
    ckpt = tmp_path / "run"
    cfg = tiny_config()
    state = CheckpointState(
        kind="student", train=TrainConfig(), epochs=1, dataset={"val_frames": [*ids[1:], 2]}
    )
    save_checkpoint(ckpt, build_model("student", cfg), cfg, state)
    args = ["steps", "--model", str(folder), "--dataset", "vod", "--data", str(vod_root), "--split", "select"]
    args += ["--steps", "1", "--threads", "1"]
    res = CliRunner().invoke(main, [*args, "--checkpoint", str(ckpt), "--out", str(tmp_path / "s")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "s" / "results.json").read_text())
    assert doc["evaluation"]["frame_ids"] == ids[1:] and "--checkpoint" in doc["command"]
    res = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "t")])
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1  # source "tests": no run
