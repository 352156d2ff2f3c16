"""``msdnet-bench quality | odometry | place`` end to end with tiny models (CliRunner)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from export_helpers import make_artifact, make_exported_checkpoint, one_torch_thread

from msdnet.benchmarks.eval_cli import odometry_command, place_command, quality_command
from msdnet.runtime.metrics.cloud import score_frame
from msdnet.runtime.metrics.crop import xy_range
from msdnet.runtime.sim.command import simulate_dataset
from msdnet.runtime.spec.grid import GRID_PRESETS

ASTYX_ARGS = ["--dataset", "astyx", "--split", "val", "--max-frames", "3", "--threads", "1"]


def _invoke(command, args: list[str]):
    with one_torch_thread():
        return CliRunner().invoke(command, args, catch_exceptions=False)


@pytest.fixture(scope="module")
def astyx_models(tmp_path_factory) -> dict[str, Path]:
    """Tiny Astyx models: a student checkpoint and its export, an R2LDM export."""
    root = tmp_path_factory.mktemp("astyx-models")
    ckpt, msdnet = make_exported_checkpoint(root, "astyx")
    return {"ckpt": ckpt, "msdnet": msdnet, "r2ldm": make_artifact(root, "r2ldm", "astyx")}


@pytest.fixture(scope="module")
def quality_run(astyx_root, astyx_models, tmp_path_factory) -> tuple[Path, Path, dict]:
    out, save = tmp_path_factory.mktemp("q") / "out", tmp_path_factory.mktemp("q") / "save"
    m = astyx_models
    args = ASTYX_ARGS + ["--data", str(astyx_root), "--out", str(out), "--save", str(save), "--pictures", "2"]
    args += ["--model", str(m["msdnet"]), "--model", str(m["r2ldm"]), "--checkpoint", str(m["ckpt"])]
    args += ["--ablation", f"w/o RGFD={m['msdnet']}"]
    r = _invoke(quality_command, args)
    assert r.exit_code == 0, r.output
    assert "within 1 %" in r.output
    return out, save, json.loads((out / "results.json").read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def sim_data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sim") / "data"
    simulate_dataset(root, sequences=2, frames=8, seed=3, progress=False)
    return root


@pytest.fixture(scope="module")
def vod_models(tmp_path_factory) -> list[str]:
    root = tmp_path_factory.mktemp("vod-models")
    return [
        "--model",
        str(make_artifact(root, "student", "vod")),
        "--model",
        str(make_artifact(root, "r2ldm", "vod")),
    ]


def test_quality_tables_and_agreement(quality_run):
    out, _, doc = quality_run
    names = [m["name"] for m in doc["methods"]]
    assert names == ["4D radar", "R2LDM (onnxruntime)", "MSDNet (onnxruntime)", "MSDNet (torch)", "w/o RGFD"]
    assert doc["evaluation"]["frames"] == 3 and len(doc["evaluation"]["frame_ids"]) == 3
    for name in names:
        s = doc["summary"][name]
        assert s["frames"] == 3 and s["cd"] > 0 and 0 <= s["fscore@0.5"] <= 1 and s["points"] > 0
    (row,) = doc["agreement"]
    assert row["ok"] and row["max_relative_difference"] <= 0.01
    assert (
        doc["margins"]["msdnet"] == "MSDNet (onnxruntime)"
        and doc["margins"]["r2ldm"] == "R2LDM (onnxruntime)"
    )
    md = (out / "results.md").read_text(encoding="utf-8")
    for text in (
        "| Method | CD (m) | CD² (m²) | MHD (m) | F@0.05 m",
        "## Ablations: scene metrics",
        "w/o RGFD",
        "Every method (the paper's Table I):",
    ):
        assert text in md
    assert "| MSDNet (torch) | MSDNet (onnxruntime) |" in md and "Paper context" in md
    assert len(doc["pictures"]) == 2 and all(
        (out / p).stat().st_size > 10_000 for p in doc["pictures"].values()
    )


def test_saved_clouds_rescore_to_the_table(quality_run):
    """Anyone scoring the --save clouds with the shared metrics gets the per-frame numbers back."""
    _, save, doc = quality_run
    index = json.loads((save / "index.json").read_text(encoding="utf-8"))
    assert [m["key"] for m in index["methods"]] == [m["key"] for m in doc["methods"]]
    area = xy_range(GRID_PRESETS["tiny"])
    for m in doc["methods"]:
        for row in doc["per_frame"][m["name"]]:
            pred = np.load(save / m["key"] / f"{row['frame']}.npy")
            ref = np.load(save / "lidar" / f"{row['frame']}.npy")
            assert pred.dtype == np.float32 and pred.shape == (row["points"], 3)
            s = score_frame(pred, ref, area)
            assert s.cd == pytest.approx(row["cd"]) and s.fscore[0.1] == pytest.approx(row["fscore@0.1"])


def test_quality_bad_input_is_one_line(astyx_root, tmp_path):
    base = ASTYX_ARGS + ["--data", str(astyx_root), "--out", str(tmp_path / "o")]
    for extra, needle in (
        (["--model", str(tmp_path / "missing")], "not an exported model folder"),
        (["--ablation", "no-equals"], "NAME=DIR"),
        (["--checkpoint", str(tmp_path)], "not a checkpoint folder"),
    ):
        r = CliRunner().invoke(quality_command, base + extra)
        assert r.exit_code == 2, r.output
        assert needle in r.output and r.output.startswith("error: ") and "Traceback" not in r.output


def test_odometry_end_to_end(sim_data, vod_models, tmp_path):
    out = tmp_path / "odo"
    r = _invoke(odometry_command, ["--data", str(sim_data), "--out", str(out), "--threads", "1"] + vod_models)
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "results.json").read_text(encoding="utf-8"))
    names = ["4D radar", "R2LDM (onnxruntime)", "MSDNet (onnxruntime)", "LiDAR", "LiDAR (full sweep)"]
    assert [m["name"] for m in doc["methods"]] == names
    for name in names:
        o = doc["results"][name]["overall"]
        assert o["pairs"] == 14 and o["translation_m"] >= 0 and o["rotation_deg"] >= 0
        assert set(doc["results"][name]["sequences"]) == {"0", "1"}
    full = doc["results"]["LiDAR (full sweep)"]["overall"]
    assert full["translation_m"] < 0.05 and full["rotation_deg"] < 0.5  # the harness itself is right
    assert "t_rel (m / frame)" in (out / "results.md").read_text(encoding="utf-8")


def test_place_end_to_end(sim_data, vod_models, tmp_path):
    out = tmp_path / "place"
    args = ["--data", str(sim_data), "--out", str(out), "--exclude-recent", "2", "--revisit-radius", "3"]
    r = _invoke(place_command, args + ["--threads", "1"] + vod_models)
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "results.json").read_text(encoding="utf-8"))
    for name, res in doc["results"].items():
        o, per = res["overall"], res["sequences"]
        assert o["queries"] == sum(p["queries"] for p in per.values()) > 0, name
        recall = [o["recall"][k] for k in ("1", "3", "5")]
        assert 0 <= recall[0] <= recall[1] <= recall[2] <= 1
        pooled = sum(p["recall"]["1"] * p["queries"] for p in per.values() if p["queries"]) / o["queries"]
        assert o["recall"]["1"] == pytest.approx(pooled)
    assert "Recall@1 (%)" in (out / "results.md").read_text(encoding="utf-8")


def test_downstream_needs_a_simulated_folder(astyx_root, tmp_path):
    r = CliRunner().invoke(odometry_command, ["--data", str(astyx_root), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "sequences.json" in r.output
    r = CliRunner().invoke(place_command, ["--data", str(astyx_root), "--out", str(tmp_path), "--ks", "0,1"])
    assert r.exit_code == 2 and "--ks" in r.output


def test_downstream_refuses_a_teacher_checkpoint(sim_data, tmp_path):
    """A teacher takes LiDAR: quality scores it on the frame's LiDAR, odometry cannot."""
    from export_helpers import make_checkpoint

    teacher = make_checkpoint(tmp_path / "teacher", "teacher", "vod")
    args = ["--data", str(sim_data), "--out", str(tmp_path / "o"), "--checkpoint", str(teacher)]
    r = CliRunner().invoke(odometry_command, args)
    assert r.exit_code == 2 and "takes LiDAR, not radar" in r.output and not (tmp_path / "o").exists()
