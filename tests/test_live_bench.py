"""A short msdnet-bench live storm on loopback: drops counted, latency bounded, restart, SIGTERM."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

pytest.importorskip("cyclonedds")

from msdnet.benchmarks.live import markdown, storm_run  # noqa: E402
from msdnet.runtime.frontends.live.dds import loopback_env  # noqa: E402
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL  # noqa: E402


def test_short_storm(vod_root: Path, tmp_path: Path) -> None:
    env = loopback_env(tmp_path)
    os.environ["CYCLONEDDS_URI"] = env["CYCLONEDDS_URI"]
    domain = 40 + os.getpid() % 180  # unique per test process; test_live_node uses 30 + pid % 180 (+1)
    files = sorted((vod_root / "radar" / "training" / "velodyne").glob("*.bin"))
    ctx = {"env": env, "model": BUNDLED_MODEL, "threads": 1, "files": files, "work": tmp_path}
    ctx["next_domain"] = lambda: domain
    s = storm_run(ctx, hz=40.0, seconds=3.0, start_ns=1_700_000_000 * 10**9)
    assert s["sent"] == 120 and s["replies"] + s["drops"] == 120
    # the node cannot serve 40 Hz; it counts every scan it dropped (its count also holds the restart's)
    assert 0 < s["drops"] <= s["node_dropped"]
    assert s["latency_bounded"], s
    assert s["restarted_publisher_served"] >= 1 and s["sigterm_within_1s"], s
    # the node runs the default provider and says which engine each graph ran on
    assert s["engines"]["provider"] == "auto", s["engines"]
    assert set(s["engines"]["graphs"]) >= {"encoder.onnx", "denoiser_step.onnx"}, s["engines"]
    assert set(s["engines"]["graphs"].values()) <= {"onnxruntime", "openvino"}
    doc = {"model": "sim-lite", "threads": 1, "note": "test", "machine": {}, "load_average": [0.0]}
    doc |= {"rates": [], "max_rate": {"max_hz_without_drops": None, "ladder": []}, "storm": s}
    doc["engines"] = s["engines"]
    page = markdown(doc)
    assert "## Storm: 40 Hz for 3 s" in page and "Engines: provider auto: encoder.onnx " in page
