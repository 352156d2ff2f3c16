"""msdnet-node stopped by a signal on a first run (empty engine cache, default provider auto):
while it loads and measures its engines, and while scans are in flight. Each exit is 0 with the
stats line and a whole stats JSON naming the state it was stopped in. ``msdnet-bench node-exit``
does the same ten and more times (docs/results/node-exit).

Every participant uses a loopback-only Cyclone configuration; domain ids are the benchmark's.
"""

from __future__ import annotations

import json
import os
import signal

import pytest

pytest.importorskip("cyclonedds")

from msdnet.benchmarks.node_exit import start_and_stop  # noqa: E402

DOMAIN = 221 + os.getpid() % 10  # and + 1; test_live_names uses 211..220, the others lower ids


def test_sigterm_while_loading_and_sigint_under_load_exit_0_with_stats(tmp_path) -> None:
    loading = start_and_stop(0, tmp_path, None, signal.SIGTERM, 1.5, None, DOMAIN)
    assert loading["ok"], loading
    assert loading["state"] in ("starting", "loading the model"), loading  # before the ready line
    stats = json.loads((tmp_path / "run-00" / "stats.json").read_text())
    assert stats["received"] == 0 and stats["stopped_while"] == loading["state"]
    assert stats["engines"]["provider"] == "auto"

    busy = start_and_stop(1, tmp_path, None, signal.SIGINT, 1.5, 20.0, DOMAIN + 1)
    assert busy["ok"], json.dumps(busy)
    assert busy["state"] == "serving" and busy["measured_engines"], busy  # a first run: it measured
    stats = json.loads((tmp_path / "run-01" / "stats.json").read_text())
    assert stats["received"] >= 1 and stats["stopped_while"] == "serving"
    assert stats["engines"]["graphs"], "a node that served names each graph's engine"
    assert busy["exit_s"] < 2.5, busy  # the scan in hand, then out
