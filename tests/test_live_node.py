"""msdnet-node on loopback: publisher process -> node process -> this process, real VoD / Astyx scans.

Every DDS participant here uses a CYCLONEDDS_URI written by the test (loopback interface,
multicast off, 127.0.0.1 the only peer) and a domain id unique to this test process.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402
from msdnet.runtime.frontends.live.dds import loopback_env  # noqa: E402
from msdnet.runtime.frontends.live.idl import PointCloud2, dds_topic  # noqa: E402
from msdnet.runtime.frontends.live.messages import cloud_message  # noqa: E402
from msdnet.runtime.frontends.live.node import LatestSlot, NodeStats  # noqa: E402
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL  # noqa: E402
from msdnet.runtime.io.files import read_cloud  # noqa: E402

DOMAIN = 30 + os.getpid() % 180  # unique per test process (parallel runs do not meet)
START = 1_700_000_000 * 10**9
HZ = 10.0
IDS = ("00549", "01047", "01201")


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict[str, str]:
    env = loopback_env(tmp_path_factory.mktemp("dds"))
    os.environ["CYCLONEDDS_URI"] = env["CYCLONEDDS_URI"]  # this process's collector too
    return env


class Node:
    """An msdnet-node process on ``domain`` and a /dense collector in this process."""

    def __init__(self, env: dict[str, str], domain: int, model: Path, tmp: Path) -> None:
        from msdnet.runtime.frontends.live.publish import DenseCollector

        self.env, self.domain, self.stats = env, domain, tmp / f"stats-{domain}.json"
        cmd = [sys.executable, "-m", "msdnet.runtime.frontends.live.cli", "--domain-id", str(domain)]
        cmd += [
            "--model",
            str(model),
            "--threads",
            "1",
            "--provider",
            "cpu",  # file mode's engine: the same bytes
            "--stats-json",
            str(self.stats),
            "--stats-every",
            "2",
        ]
        self.proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        ready = self.proc.stdout.readline()
        assert "serving /radar/points (DDS rt/radar/points" in ready, ready + self.proc.stderr.read()
        self.collector = DenseCollector("/radar/points", domain)
        self.collector.wait_matched()

    def publish(self, files: list[Path], count: int, start: int = START, bad: tuple[int, ...] = ()) -> None:
        cmd = [sys.executable, "-m", "msdnet.runtime.frontends.live.publish", *map(str, files)]
        cmd += ["--domain-id", str(self.domain), "--hz", str(HZ), "--count", str(count)]
        cmd += ["--start-ns", str(start), *(a for i in bad for a in ("--bad", str(i)))]
        cmd += ["--lockstep", "30"]  # one reply per good scan however loaded the machine is
        r = subprocess.run(cmd, env=self.env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr

    def stop(self) -> tuple[float, str, str, dict]:
        """SIGTERM -> (seconds to exit, stdout, stderr, stats JSON)."""
        self.collector.close()
        start = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        out, err = self.proc.communicate(timeout=10)
        seconds = time.monotonic() - start
        assert self.proc.returncode == 0, err
        return seconds, out, err, json.loads(self.stats.read_text())


def _file_mode(model: Path, files: list[Path]) -> list[np.ndarray]:
    pipe = Pipeline.from_dir(model, threads=1)
    out = []
    for f in files:
        res = pipe(read_cloud(f), seed=0)
        out.append(np.concatenate([res.points, res.confidence[:, None]], axis=1))
    return out


def _check_equal(received, expected: list[np.ndarray], start: int) -> None:
    for stamp, _, dense in received:
        i = round((stamp - start) * HZ / 1e9)
        assert np.array_equal(dense, expected[i % len(expected)]), f"message {i} differs from file mode"


def test_vod_scans_equal_file_mode_bad_message_publisher_restart_sigterm(env, vod_root, tmp_path) -> None:
    files = [vod_root / "radar" / "training" / "velodyne" / f"{i}.bin" for i in IDS]
    expected = _file_mode(BUNDLED_MODEL, files)
    node = Node(env, DOMAIN, BUNDLED_MODEL, tmp_path)
    try:
        node.publish(files, 4, bad=(1,))  # message 1 malformed: counted, and the node goes on
        assert node.collector.wait_for(3, 10)
        first = list(node.collector.received)
        restart = START + 10**9 * 100  # a second publisher process, after the first one exited
        node.publish(files, 2, start=restart)
        assert node.collector.wait_for(len(first) + 2, 10), "a publisher that came back is not served"
    finally:
        seconds, out, err, stats = node.stop()
    again = node.collector.received[len(first) :]
    assert len(first) == 3 and len(again) == 2, (out, err)  # one dense cloud per good scan
    _check_equal(first, expected, START)
    _check_equal(again, expected, restart)
    assert stats["bad"] == 1 and stats["received"] == 6 and stats["dropped"] == 0
    assert stats["published"] == len(node.collector.received)
    bad = [line for line in err.splitlines() if "bad message" in line]
    assert len(bad) == 1 and "message 1 " in bad[0] and "Traceback" not in err
    assert "receive->publish ms p50" in out.splitlines()[-1] and out.count("msdnet-node: received") >= 3
    assert seconds < 1.0, f"SIGTERM -> exit took {seconds:.2f} s"


def test_astyx_scans_equal_file_mode(env, astyx_root, tmp_path) -> None:
    model = BUNDLED_MODEL.parent / "astyx-lite"
    files = [astyx_root / "radar_6455" / f"{i:06d}.txt" for i in range(3)]
    expected = _file_mode(model, files)
    node = Node(env, DOMAIN + 1, model, tmp_path)
    try:
        node.publish(files, 3)
        node.collector.wait_for(3, 10)
    finally:
        _, out, err, stats = node.stop()
    assert len(node.collector.received) == 3, (out, err)
    _check_equal(node.collector.received, expected, START)
    assert stats["bad"] == 0 and stats["published"] == 3


def test_latest_message_wins_and_stats() -> None:
    slot, stats = LatestSlot(), NodeStats()
    assert slot.put("a") is False and slot.put("b") is True  # "a" was replaced: one drop
    assert slot.take(0.01) == "b" and slot.take(0.01) is None
    stats.latencies.extend([0.010, 0.020, 0.030, 0.100])
    lat = stats.summary()["latency_ms"]
    assert lat["max"] == pytest.approx(100.0) and lat["p50"] == pytest.approx(25.0) and lat["count"] == 4
    assert stats.latencies.maxlen is not None  # bounded memory


def test_idl_names_and_fast_bytes_keep_the_wire_format() -> None:
    from live_generic_idl import GenericPointCloud2

    assert PointCloud2.__idl__.idl_transformed_typename == "sensor_msgs::msg::dds_::PointCloud2_"
    assert dds_topic("/radar/points") == "rt/radar/points" == dds_topic("radar/points")
    with pytest.raises(Exception, match="not a ROS 2 topic"):
        dds_topic("/radar//points")
    msg = cloud_message(np.arange(21, dtype=np.float32).reshape(3, 7), list("xyzabcd"), (5, 6), "radar")
    generic = GenericPointCloud2(msg.header, 1, 3, msg.fields, False, 28, 84, list(msg.data), True)
    assert msg.serialize() == generic.serialize()
    assert PointCloud2.deserialize(generic.serialize()).data == msg.data
