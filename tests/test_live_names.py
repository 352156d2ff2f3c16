"""Two msdnet-nodes on one DDS domain, told apart by --node-name and --namespace: each publishes its
own ~/debug topics and its own diagnostic status (name and hardware id), /diagnostics comes at the
fixed period whether scans come or not, and a writer of another type on a node's input topic is
named once in one line. Also the start-up checks of what the parameters mean together.

Every DDS participant uses a CYCLONEDDS_URI written by the test (loopback interface, multicast off,
127.0.0.1 the only peer) and a domain id unique to this test process.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("cyclonedds")

from msdnet.runtime.frontends.live.dds import Endpoints, loopback_env  # noqa: E402
from msdnet.runtime.frontends.live.idl import AutowareFloat64Stamped, DiagnosticArray, dds_topic  # noqa: E402
from msdnet.runtime.frontends.live.publish import DenseCollector  # noqa: E402

DOMAIN = 211 + os.getpid() % 10  # per test process; test_live_exit uses 221..231, the others lower ids
NODE = [sys.executable, "-m", "msdnet.runtime.frontends.live.cli"]
PERIOD_S = 0.25  # the nodes' diagnostics period here
START = 1_700_000_000 * 10**9


class Readers:
    """Reliable readers of both nodes' processing_time_ms and of /diagnostics, in a thread."""

    def __init__(self, domain: int, debug_topics: list[str]) -> None:
        self.dds = Endpoints(domain)
        self.readers = {
            t: self.dds.reader(dds_topic(t), True, 1000, AutowareFloat64Stamped) for t in debug_topics
        }
        self.readers["/diagnostics"] = self.dds.reader(dds_topic("/diagnostics"), True, 1000, DiagnosticArray)
        self.got: dict[str, list] = {t: [] for t in self.readers}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            for name, reader in self.readers.items():
                for s in reader.take(N=100):
                    if s.sample_info.valid_data:
                        self.got[name].append((time.monotonic(), s))
            time.sleep(0.02)

    def matched(self) -> bool:
        return all(r.get_matched_publications() for r in self.readers.values())

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1)
        self.dds.close()


def _wait(cond, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.05)
    return cond()


def _node(env: dict[str, str], args: list[str]) -> subprocess.Popen:
    proc = subprocess.Popen(NODE + args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ready = proc.stdout.readline()
    assert "serving" in ready, ready + proc.stderr.read()
    return proc


def _publish(env: dict[str, str], files: list[Path], topic: str, count: int) -> None:
    cmd = [sys.executable, "-m", "msdnet.runtime.frontends.live.publish", *map(str, files), "--topic", topic]
    cmd += ["--domain-id", str(DOMAIN), "--hz", "10", "--count", str(count), "--start-ns", str(START)]
    cmd += ["--lockstep", "30"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_two_named_nodes_on_one_domain(vod_root, tmp_path) -> None:
    env = loopback_env(tmp_path)
    os.environ["CYCLONEDDS_URI"] = env["CYCLONEDDS_URI"]
    files = [vod_root / "radar" / "training" / "velodyne" / f"{i}.bin" for i in ("00549", "01047")]
    common = ["--domain-id", str(DOMAIN), "--provider", "cpu", "--threads", "1"]
    common += ["--diagnostics-period", str(PERIOD_S)]
    front = _node(env, [*common, "--node-name", "radar_front", "--topic", "/front/points"])
    rear_stats = tmp_path / "rear.json"
    rear = _node(  # RadarScan input, in a namespace, a relative topic resolved under it
        env,
        [*common, "--node-name", "radar_rear", "--namespace", "/sensing", "--topic", "rear/points"]
        + ["--input-type", "radar_scan", "--stats-json", str(rear_stats)],
    )
    debug = ["/radar_front/debug/processing_time_ms", "/sensing/radar_rear/debug/processing_time_ms"]
    readers = Readers(DOMAIN, debug)
    collector = DenseCollector("/front/points", DOMAIN)
    try:
        collector.wait_matched()
        assert _wait(readers.matched, 20), "a node's debug topic or /diagnostics is not there"
        _publish(env, files, "/front/points", 3)
        for _ in range(2):  # a PointCloud2 writer on the RadarScan node's topic, twice: named once
            other = Endpoints(DOMAIN)
            other.writer(dds_topic("/sensing/rear/points"))
            time.sleep(1.0)
            other.close()
        assert collector.wait_for(3, 20)
        time.sleep(1.5)  # idle: /diagnostics still comes at the period
    finally:
        collector.close()
        readers.close()
        outs = {}
        for name, proc in (("front", front), ("rear", rear)):
            proc.send_signal(signal.SIGTERM)
            outs[name] = proc.communicate(timeout=20)
            assert proc.returncode == 0, outs[name][1]

    # separate debug topics: the front node's scans on its own, none on the rear node's
    assert len(readers.got[debug[0]]) == 3 and readers.got[debug[1]] == []
    # diagnostics: one status name and hardware id per node, as diagnostic_updater names them
    statuses: dict[str, list] = {}
    for at, msg in readers.got["/diagnostics"]:
        (status,) = msg.status
        statuses.setdefault(status.name, []).append((at, status))
    assert set(statuses) == {"radar_front: processing_time", "radar_rear: processing_time"}
    hardware = {name: {s.hardware_id for _, s in seq} for name, seq in statuses.items()}
    assert hardware["radar_front: processing_time"] == {"radar_front /front/points"}
    assert hardware["radar_rear: processing_time"] == {"sensing/radar_rear /sensing/rear/points"}
    # at the fixed period, whether scans came or not: the gaps between a node's messages
    for seq in statuses.values():
        gaps = [b[0] - a[0] for a, b in zip(seq, seq[1:], strict=False)]
        assert len(seq) >= 8 and 0.5 * PERIOD_S < sorted(gaps)[len(gaps) // 2] < 1.6 * PERIOD_S, gaps
    # the writer of another type: one line, named once, counted
    err = outs["rear"][1]
    lines = [line for line in err.splitlines() if "is not matched" in line]
    assert len(lines) == 1 and "publishes sensor_msgs/msg/PointCloud2" in lines[0], err
    assert "radar_msgs/msg/RadarScan" in lines[0] and "Traceback" not in err
    stats = json.loads(rear_stats.read_text())
    assert stats["unmatched_writers"] == 1 and stats["received"] == 0


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--output-topic", "/radar/points"], "--output-topic: /radar/points is both the input topic"),
        (
            ["--output-topic", "/msdnet_node/debug/cyclic_time_ms"],
            "already the node's ~/debug/cyclic_time_ms",
        ),
        (["--topic", "/diagnostics"], "--topic: /diagnostics is both the input topic"),
        (["--node-name", "9lives"], "--node-name: '9lives' is not a ROS 2 node name"),
        (["--namespace", "/a//b"], "--namespace: '/a//b' is not a ROS 2 namespace"),
        (["--input-type", "radar_scan", "--field", "rcs=intensity"], "--field: a RadarScan has no field"),
        (["--target-frame", "b", "--extrinsic", "1e39,0,0,0,0,0"], "beyond float32"),
        (["--target-frame", "b", "--extrinsic", "1e9,0,0,0,0,0"], "coarser than the voxels"),
        (["--threads", "100000"], "--threads: must be <= 256"),
        (["--diagnostics-period", "0"], "--diagnostics-period: must be >= 0.01"),
    ],
)
def test_options_that_cannot_apply_are_refused_at_start(args: list[str], says: str) -> None:
    r = subprocess.run(NODE + ["--provider", "cpu", *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and says in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_values_from_a_parameters_file_name_the_file_and_key(tmp_path) -> None:
    path = tmp_path / "node.yaml"
    path.write_text(
        "msdnet_node:\n  ros__parameters:\n    target_frame: base_link\n    extrinsic: '1e39,0,0,0,0,0'\n",
        encoding="utf-8",
    )
    r = subprocess.run(NODE + ["--params-file", str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and f"error: {path}: extrinsic: " in r.stderr, r.stderr
    path.write_text("msdnet_node:\n  ros__parameters:\n    output_topic: /radar/points\n", encoding="utf-8")
    r = subprocess.run(NODE + ["--params-file", str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and f"error: {path}: output_topic: " in r.stderr, r.stderr
