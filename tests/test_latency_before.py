"""``msdnet-bench latency --before``: the previous pipeline against the new one, same run and scans,
and the ratios it records (no timing assertions: only that they are there and positive)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from click.testing import CliRunner
from export_helpers import make_artifact

from msdnet.benchmarks.latency.cli import latency_command

RATIOS = ("frame_over_before", "encoder_over_before")


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_artifact(tmp_path_factory.mktemp("before-art"), "student")


def _run(out: Path, *args: str) -> dict:
    r = CliRunner().invoke(latency_command, ["--quick", "--no-int8", "--out", str(out), *args])
    assert r.exit_code == 0, r.output
    return json.loads((out / "results.json").read_text(encoding="utf-8"))


def _positive(x: object) -> bool:
    return isinstance(x, float) and math.isfinite(x) and x > 0


def test_before_the_same_model_records_finite_ratios_beside_the_peers(model, tmp_path):
    res = _run(tmp_path / "o", "--model", str(model), "--before", str(model))
    for key in (*RATIOS, "engine_over_best_peer"):
        assert _positive(res["ratios"][key]), key
    b = res["before"]
    assert res["provider"] == "auto" and b["new"]["provider"] == b["before"]["provider"] == "auto"
    assert b["scans"] == 3 and b["source"] == "3 seeded synthetic scans of 300 points"
    assert b["frame_over_before"] == res["ratios"]["frame_over_before"]
    assert b["frame_over_before"] == pytest.approx(b["new"]["total_ms"] / b["before"]["total_ms"])
    assert len(b["encoder_over_before_per_scan"]) == 3 and _positive(b["encoder_over_before_paired_median"])
    assert b["before"]["folder"] == str(model) and b["new"]["steps"] == b["before"]["steps"]
    assert b["new"]["head"] == b["before"]["head"]  # the same model, run as msdnet-infer runs it
    md = (tmp_path / "o" / "results.md").read_text(encoding="utf-8")
    assert "## Against the previous pipeline (--before)" in md and "`frame_over_before`" in md


def test_before_without_peers_or_stream_times_seeded_scans_and_no_peer_ratio(model, tmp_path):
    args = ("--model", str(model), "--before", str(model), "--no-peers", "--stream-frames", "0")
    res = _run(tmp_path / "o", *args, "--provider", "cpu")
    assert all(_positive(res["ratios"][k]) for k in RATIOS)
    assert res["ratios"]["engine_over_best_peer"] is None  # no peers: null, not a number
    assert res["before"]["new"]["engines"]["encoder.onnx"] == "onnxruntime"
    assert res["before"]["source"].endswith("seeded synthetic scans of 300 points")


def test_before_must_be_a_model_folder(tmp_path):
    r = CliRunner().invoke(
        latency_command, ["--quick", "--out", str(tmp_path / "o"), "--before", str(tmp_path)]
    )
    assert r.exit_code == 2 and r.output.strip().splitlines()[-1].startswith("error: --before: ")
