"""msdnet-node as a ROS 2 stack expects it: parameters file, RadarScan input, output frame and
fields, debug topics and /diagnostics, Foxglove, messages that disagree with their header, the
stats path checked at start, and a 100 MB PointCloud2 over loopback.

Every DDS participant uses a CYCLONEDDS_URI written by the test (loopback interface, multicast
off, 127.0.0.1 the only peer) and a domain id unique to this test process; the Foxglove server
binds 127.0.0.1.
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

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402
from msdnet.runtime.engine.pointcloud import PointCloud  # noqa: E402
from msdnet.runtime.engine.voxelize import in_range_mask  # noqa: E402
from msdnet.runtime.frontends.live.dds import Endpoints, loopback_env  # noqa: E402
from msdnet.runtime.frontends.live.idl import (  # noqa: E402
    AutowareFloat64Stamped,
    DiagnosticArray,
    DiagnosticStatus,
    Header,
    KeyValue,
    RadarScan,
    Tier4Float64Stamped,
    Time,
    dds_topic,
)
from msdnet.runtime.frontends.live.messages import (  # noqa: E402
    cloud_message,
    message_cloud,
    polar_to_points,
    radar_scan_message,
)
from msdnet.runtime.frontends.live.publish import NONFINITE_ROWS, DenseCollector, scan_returns  # noqa: E402
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL  # noqa: E402
from msdnet.runtime.io.files import read_cloud  # noqa: E402
from msdnet.runtime.io.pairing.transforms import parse_extrinsic  # noqa: E402

DOMAIN = 60 + os.getpid() % 150  # unique per test process; test_live_node / _bench use 30.. / 40..
START = 1_700_000_000 * 10**9
IDS = ("00549", "01047", "01201")
NODE = [sys.executable, "-m", "msdnet.runtime.frontends.live.cli"]
EXTRINSIC = "1.5,0.2,0.8,0.0,0.02,0.1"


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict[str, str]:
    env = loopback_env(tmp_path_factory.mktemp("dds"))
    os.environ["CYCLONEDDS_URI"] = env["CYCLONEDDS_URI"]  # this process's readers too
    return env


def _vod(vod_root: Path) -> list[Path]:
    return [vod_root / "radar" / "training" / "velodyne" / f"{i}.bin" for i in IDS]


def _start(env: dict[str, str], args: list[str]) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(NODE + args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ready = proc.stdout.readline()
    assert "serving" in ready, ready + proc.stderr.read()
    return proc, ready


def _stop(proc: subprocess.Popen) -> tuple[str, str]:
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    return out, err


def _publish(env: dict[str, str], domain: int, files: list[Path], count: int, *extra: str) -> None:
    cmd = [sys.executable, "-m", "msdnet.runtime.frontends.live.publish", *map(str, files)]
    cmd += ["--domain-id", str(domain), "--hz", "10", "--count", str(count), "--start-ns", str(START)]
    cmd += ["--lockstep", "30", *extra]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


class Listener:
    """Reliable readers of the node ``fqn``'s debug topics and /diagnostics, collecting in a thread."""

    def __init__(self, domain: int, debug_struct: type, fqn: str = "/msdnet_node") -> None:
        self.dds = Endpoints(domain)
        names = ("processing_time_ms", "cyclic_time_ms", "pipeline_latency_ms")
        self.readers = {
            n: self.dds.reader(dds_topic(f"{fqn}/debug/{n}"), True, 1000, debug_struct) for n in names
        }
        self.readers["diagnostics"] = self.dds.reader(dds_topic("/diagnostics"), True, 1000, DiagnosticArray)
        self.got: dict[str, list] = {n: [] for n in self.readers}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            for name, reader in self.readers.items():
                for s in reader.take(N=100):
                    if s.sample_info.valid_data:
                        self.got[name].append(s)
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


def _print_params(*args: str) -> str:
    r = subprocess.run(NODE + [*args, "--print-params"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_params_file_equals_flags(tmp_path) -> None:
    flags = ["--topic", "/radar/scan", "--input-type", "radar_scan", "--threads", "1", "--keep-radar"]
    flags += ["--field", "rcs=amplitude", "--field", "v_r_compensated=v_r", "--no-publish-debug"]
    flags += ["--max-allowed-processing-time-ms", "80", "--target-frame", "base_link"]
    flags += ["--extrinsic", EXTRINSIC, "--debug-msgs-type", "tier4_debug_msgs"]
    from_flags = _print_params(*flags)
    path = tmp_path / "node.yaml"
    path.write_text(from_flags, encoding="utf-8")  # the dump is itself a parameters file
    assert _print_params("--params-file", str(path)) == from_flags
    hand = tmp_path / "hand.yaml"
    hand.write_text(
        "/**:\n  ros__parameters:\n    threads: 4\n"
        "msdnet_node:\n  ros__parameters:\n"
        "    input_topic: /radar/scan\n    input_type: radar_scan\n    threads: 1\n    keep_radar: true\n"
        "    fields: [rcs=amplitude, v_r_compensated=v_r]\n    publish_debug: false\n"
        "    max_allowed_processing_time_ms: 80\n    target_frame: base_link\n"
        f"    extrinsic: '{EXTRINSIC}'\n    debug_msgs_type: tier4_debug_msgs\n"
        "other_node:\n  ros__parameters:\n    anything: 1\n",
        encoding="utf-8",
    )
    assert _print_params("--params-file", str(hand)) == from_flags
    # a flag given on the command line wins over the file
    assert "threads: 3" in _print_params("--params-file", str(hand), "--threads", "3")


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("msdnet_node:\n  ros__parameters:\n    bogus: 1\n", "unknown parameter 'bogus'"),
        ("msdnet_node:\n  ros__parameters:\n    threads: two\n", "threads: expected an integer"),
        ("msdnet_node:\n  ros__parameters:\n    keep_radar: 1\n", "keep_radar: expected a bool"),
        ("msdnet_node:\n  ros__parameters:\n    input_type: laser\n", "input_type: must be one of"),
        ("msdnet_node:\n  ros__parameters:\n    seed: -1\n", "seed: must be >= 0"),
        ("msdnet_node:\n  threads: 1\n", "expected only 'ros__parameters:'"),
        ("other:\n  ros__parameters: {}\n", "no 'msdnet_node: ros__parameters:' section"),
        ("msdnet_node: [\n", "not YAML"),
    ],
)
def test_bad_params_file_is_one_line(tmp_path, text: str, says: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text, encoding="utf-8")
    r = subprocess.run(NODE + ["--params-file", str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and says in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--target-frame", "base_link"], "--target-frame: needs --extrinsic"),
        (["--extrinsic", "1,2,3"], "--target-frame: needs --extrinsic"),
        (["--target-frame", "b", "--extrinsic", "1,2,3"], "--extrinsic: expected six numbers"),
        (["--input-type", "radar_scan", "--field-preset", "vod"], "--field-preset: applies to PointCloud2"),
        (["--field", "nope=x"], "--field: the model has no column 'nope'"),
        (["--testing-delay", "5"], "--testing-delay: expected START:STOP:MS"),
    ],
)
def test_bad_flags_are_one_line(args: list[str], says: str) -> None:
    r = subprocess.run(NODE + args, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and says in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_stats_json_checked_before_any_work(tmp_path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("x", encoding="utf-8")
    start = time.monotonic()
    r = subprocess.run(
        NODE + ["--stats-json", str(blocker / "stats.json")], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 2 and str(blocker / "stats.json") in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert time.monotonic() - start < 20  # refused before the model is loaded or DDS joined
    r = subprocess.run(NODE + ["--stats-json", str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "is a folder" in r.stderr, r.stderr


def test_messages_round_trip_an_independent_cdr_encoder() -> None:
    """rosbags' CDR serializer (types from the published .msg text) and the node's IDL structs
    write the same bytes, and each reads the other's."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    msgs = {
        "radar_msgs/msg/RadarReturn": "float32 range\nfloat32 azimuth\nfloat32 elevation\n"
        "float32 doppler_velocity\nfloat32 amplitude\n",
        "radar_msgs/msg/RadarScan": "std_msgs/Header header\nradar_msgs/RadarReturn[] returns\n",
        "tier4_debug_msgs/msg/Float64Stamped": "builtin_interfaces/Time stamp\nfloat64 data\n",
        "autoware_internal_debug_msgs/msg/Float64Stamped": "builtin_interfaces/Time stamp\nfloat64 data\n",
    }
    for name, text in msgs.items():
        store.register(get_types_from_msg(text, name))
    t = store.types
    rng = np.random.default_rng(0)
    returns = rng.normal(size=(37, 5)).astype(np.float32)
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=12, nanosec=34), frame_id="radar"
    )
    scan = t["radar_msgs/msg/RadarScan"](
        header=header, returns=[t["radar_msgs/msg/RadarReturn"](*map(float, row)) for row in returns]
    )
    raw = store.serialize_cdr(scan, "radar_msgs/msg/RadarScan")
    ours = RadarScan.deserialize(bytes(raw))
    assert np.array_equal(ours.returns, returns) and ours.header.frame_id == "radar"
    assert (ours.header.stamp.sec, ours.header.stamp.nanosec) == (12, 34)
    assert radar_scan_message(returns, (12, 34), "radar").serialize() == bytes(raw)
    back = store.deserialize_cdr(
        radar_scan_message(returns, (12, 34), "radar").serialize(), "radar_msgs/msg/RadarScan"
    )
    assert len(back.returns) == 37 and np.float32(back.returns[5].doppler_velocity) == returns[5, 3]

    status = t["diagnostic_msgs/msg/DiagnosticStatus"](
        level=2,
        name="msdnet_node: processing_time",
        message="slow",
        hardware_id="hw",
        values=[t["diagnostic_msgs/msg/KeyValue"](key="k", value="v")],
    )
    array = t["diagnostic_msgs/msg/DiagnosticArray"](header=header, status=[status])
    raw = bytes(store.serialize_cdr(array, "diagnostic_msgs/msg/DiagnosticArray"))
    mine = DiagnosticArray(
        Header(Time(12, 34), "radar"),
        [DiagnosticStatus(2, "msdnet_node: processing_time", "slow", "hw", [KeyValue("k", "v")])],
    )
    assert mine.serialize() == raw and DiagnosticArray.deserialize(raw).status[0].level == 2
    for struct, name in (
        (Tier4Float64Stamped, "tier4_debug_msgs/msg/Float64Stamped"),
        (AutowareFloat64Stamped, "autoware_internal_debug_msgs/msg/Float64Stamped"),
    ):
        raw = bytes(
            store.serialize_cdr(
                t[name](stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=2), data=3.25), name
            )
        )
        assert struct(Time(1, 2), 3.25).serialize() == raw and struct.deserialize(raw).data == 3.25
    assert RadarScan.__idl__.idl_transformed_typename == "radar_msgs::msg::dds_::RadarScan_"
    assert (
        DiagnosticStatus.__idl__.idl_transformed_typename == "diagnostic_msgs::msg::dds_::DiagnosticStatus_"
    )


def test_pointcloud2_saying_less_or_more_than_it_holds_is_refused() -> None:
    import dataclasses

    msg = cloud_message(np.ones((352, 4), np.float32), list("xyzw"), (1, 2), "radar")
    for width, row in ((100, 1600), (352, 352 * 16), (400, 6400)):
        bad = dataclasses.replace(msg, width=width, row_step=row)
        if width == 352:
            bad = dataclasses.replace(bad, data=bytes(msg.data) + bytes(16))  # one row more than said
        if width * 16 == len(bad.data):
            continue
        with pytest.raises(Exception, match="refusing to cut|need more") as info:
            message_cloud(bad, ("x", "y", "z"), {}, "message 0")
        assert str(info.value).startswith("message 0: ")
    cloud, names = message_cloud(msg, ("x", "y", "z", "w"), {}, "ok")
    assert cloud.points.shape == (352, 4) and names == ("x", "y", "z", "w")


def test_radar_scan_presets_map_fields() -> None:
    from msdnet.runtime.frontends.live.messages import field_mapping

    cols = ("x", "y", "z", "rcs", "v_r_compensated")
    assert field_mapping(["x", "y", "z", "rcs", "range_rate"], cols, {}, "ars548") == {
        "rcs": "rcs",
        "v_r_compensated": "range_rate",
    }
    assert field_mapping(["x", "y", "z", "intensity", "velocity"], cols, {}, "ti")["rcs"] == "intensity"
    astyx = field_mapping(["x", "y", "z", "v_r", "Magnitude"], ("x", "y", "z", "v_r", "mag"), {}, "astyx")
    assert astyx == {"v_r": "v_r", "mag": "Magnitude"}
    assert field_mapping(["x", "y", "z", "RCS"], cols, {"rcs": "other"}, "vod")["rcs"] == "other"
    # polar -> cartesian, REP 103: azimuth anticlockwise from x, elevation up
    pts = polar_to_points(np.array([[10.0, np.pi / 2, 0.0, 1.0, 2.0], [2.0, 0.0, np.pi / 6, 0, 0]]))
    assert np.allclose(pts[0, :3], [0, 10, 0], atol=1e-5) and np.allclose(pts[1, :3], [np.sqrt(3), 0, 1])


def _send(domain: int, msgs: list, collector: DenseCollector, struct: type) -> None:
    """Write ``msgs`` from this process (reliable), each after the reply to the one before."""
    from msdnet.runtime.frontends.live.publish import wait_matched

    dds = Endpoints(domain)
    try:
        writer = dds.writer(dds_topic("/radar/points"), reliable=True, struct=struct)
        wait_matched(writer.get_matched_subscriptions, "the node")
        time.sleep(0.3)
        for i, msg in enumerate(msgs):
            writer.write(msg)
            assert collector.wait_for(i + 1, 30)
    finally:
        dds.close()


def test_radar_scan_input_equals_pointcloud2_input(env, vod_root) -> None:
    """The same VoD scans sent as RadarScan (one node) and as PointCloud2 with fields x y z v_r
    amplitude (another node, mapped by --field) give the same dense clouds, byte for byte, with
    the input header; both publishers reliable (the node's sensor-data reader takes those too)."""
    returns = []
    for f in _vod(vod_root):
        c = read_cloud(f)
        returns.append(scan_returns(c.points, c.columns, "v_r_compensated", "rcs"))
    stamps = [divmod(START + i * 10**8, 10**9) for i in range(len(returns))]
    scans = [radar_scan_message(r, st, "radar_front") for r, st in zip(returns, stamps, strict=True)]
    names = ["x", "y", "z", "v_r", "amplitude"]
    clouds = [
        cloud_message(polar_to_points(r), names, st, "radar_front")
        for r, st in zip(returns, stamps, strict=True)
    ]
    got = {}
    for kind, msgs, extra in (
        ("radar_scan", scans, []),
        ("pointcloud2", clouds, ["--field", "rcs=amplitude", "--field", "v_r_compensated=v_r"]),
    ):
        if kind == "pointcloud2":  # and the output publisher's reliability as a parameter
            extra = [*extra, "--output-reliability", "best_effort"]  # a best-effort reader
        domain = DOMAIN + (0 if kind == "radar_scan" else 2)
        proc, ready = _start(
            env,
            ["--domain-id", str(domain), "--input-type", kind, "--threads", "1", "--provider", "cpu", *extra],
        )
        collector = DenseCollector("/radar/points", domain, reliable=kind == "radar_scan")
        try:
            collector.wait_matched()
            _send(domain, msgs, collector, RadarScan if kind == "radar_scan" else type(clouds[0]))
        finally:
            collector.close()
            out, err = _stop(proc)
        assert len(collector.received) == len(msgs), (out, err)
        got[kind] = collector.received
        if kind == "radar_scan":
            assert "RadarScan" in ready and "v_r_compensated is fed the uncompensated radial velocity" in err
    for (s1, _, d1), (s2, _, d2), st in zip(got["radar_scan"], got["pointcloud2"], stamps, strict=True):
        assert s1 == s2 == st[0] * 10**9 + st[1]  # the input stamp, kept
        assert d1.shape[0] > 100 and np.array_equal(d1, d2), "RadarScan and PointCloud2 outputs differ"


def test_stack_node_params_file_keep_radar_frame_diagnostics_debug_foxglove(env, vod_root, tmp_path) -> None:
    """One node from a parameters file: keep_radar fields and a target frame; the diagnostics go
    OK -> WARN -> ERROR -> OK under an artificial delay; the debug topics agree with the node's own
    percentiles; a Foxglove client gets both clouds for every scan; dropped points counted."""
    from live_ws_client import FoxgloveClient

    domain = DOMAIN + 1
    stats_path = tmp_path / "out" / "stats.json"
    params = tmp_path / "node.yaml"
    params.write_text(
        "msdnet_node:\n  ros__parameters:\n"
        f"    domain_id: {domain}\n    threads: 1\n    provider: cpu\n    keep_radar: true\n"
        f"    target_frame: base_link\n    extrinsic: '{EXTRINSIC}'\n"
        "    debug_msgs_type: tier4_debug_msgs\n"
        "    max_allowed_processing_time_ms: 600.0\n    max_acceptable_consecutive_delay_ms: 1200.0\n"
        "    testing_delay: '4:8:800'\n    foxglove: true\n    foxglove_port: 0\n"
        "    diagnostics_period_s: 0.1\n    node_name: stack_node\n"  # its own status among any others
        f"    stats_json: {stats_path}\n",
        encoding="utf-8",
    )
    files = _vod(vod_root)
    count = 14
    nonfinite = (2, 9)  # these scans carry NONFINITE_ROWS rows with NaN / Inf
    proc, ready = _start(env, ["--params-file", str(params)])
    port = int(ready.rsplit(":", 1)[1])
    assert "ws://127.0.0.1:" in ready
    fox = FoxgloveClient(port, ("/radar/points", "/radar/points/dense"))
    listener = Listener(domain, Tier4Float64Stamped, "/stack_node")
    collector = DenseCollector("/radar/points", domain)
    try:
        collector.wait_matched()
        assert _wait(listener.matched, 20) and _wait(fox.ready, 20)
        _publish(env, domain, files, count, *(a for i in nonfinite for a in ("--nonfinite", str(i))))
        assert collector.wait_for(count, 30)
        _wait(lambda: len(listener.got["processing_time_ms"]) >= count, 5)
        time.sleep(0.3)
    finally:
        collector.close()
        out, err = _stop(proc)
        listener.close()
        fox.close()
    stats = json.loads(stats_path.read_text())
    assert stats["published"] == count and stats["bad"] == 0, (out, err)

    # output: input stamp, target frame, x y z confidence + the input's own fields of kept points
    pipe = Pipeline.from_dir(BUNDLED_MODEL, threads=1)
    transform = parse_extrinsic(EXTRINSIC)
    assert set(collector.frames) == {"base_link"}
    assert set(collector.fields) == {("x", "y", "z", "confidence", "rcs", "v_r_compensated")}
    for stamp, _, dense in collector.received:
        i = round((stamp - START) * 10 / 1e9)
        cloud = read_cloud(files[i % len(files)])
        pts = pipe.select_columns(cloud)[NONFINITE_ROWS if i in nonfinite else 0 :]
        radar = pts[in_range_mask(pts, pipe.artifact.grid)]
        kept = len(radar)
        assert kept > 0 and dense.shape[1] == 6 and dense.shape[0] > kept
        assert np.array_equal(dense[-kept:, 4:], radar[:, 3:]) and (dense[-kept:, 3] == 1.0).all()
        want = radar[:, :3].astype(np.float64) @ transform[:3, :3].T + transform[:3, 3]
        assert np.allclose(dense[-kept:, :3], want, atol=1e-5)
        assert np.isnan(dense[:-kept, 4:]).all()
        res = pipe(PointCloud(pts, pipe.columns), seed=0, keep_radar=True)  # file mode, same engine
        model = res.points.astype(np.float64) @ transform[:3, :3].T + transform[:3, 3]
        assert np.array_equal(dense[:, 3], res.confidence) and np.allclose(dense[:, :3], model, atol=1e-5)
        assert (dense[:-kept, 3] > 0.0).all()

    # dropped input points: per scan and in the totals (stats line and JSON)
    pts = stats["input_points"]
    assert pts["dropped_nonfinite"] == NONFINITE_ROWS * len(nonfinite) and pts["dropped_outside_grid"] > 0
    per_scan = stats["input_points_per_scan"]
    assert len(per_scan) == count and [s["dropped_nonfinite"] for s in per_scan].count(NONFINITE_ROWS) == 2
    assert pts["dropped"] == sum(
        pts[k] for k in ("dropped_nonfinite", "dropped_outside_grid", "dropped_over_cap")
    )
    assert sum(s["dropped_nonfinite"] for s in stats["input_points_per_scan"]) == pts["dropped_nonfinite"]
    assert f"with NaN/Inf {pts['dropped_nonfinite']}" in out.splitlines()[-1]
    assert "points with NaN/Inf dropped" in err

    # diagnostics OK -> WARN -> ERROR -> OK, at the period (this node's status: others may share the bus)
    ours = [
        s.status[0] for s in listener.got["diagnostics"] if s.status[0].name == "stack_node: processing_time"
    ]
    levels = [s.level for s in ours]
    changes = [lv for j, lv in enumerate(levels) if j == 0 or lv != levels[j - 1]]
    assert changes == [0, 1, 2, 0], [(s.level, s.message) for s in ours]
    assert stats["diagnostics"]["WARN"] >= 1 and stats["diagnostics"]["ERROR"] >= 1
    status = ours[-1]
    assert status.hardware_id == "stack_node /radar/points" and status.level == 0
    assert {kv.key for kv in status.values} >= {"processing_time_ms", "max_allowed_processing_time_ms"}

    # debug topics: the node's own percentiles within 5 %
    for topic, key in (
        ("processing_time_ms", "processing_time_ms"),
        ("cyclic_time_ms", "cyclic_time_ms"),
        ("pipeline_latency_ms", "pipeline_latency_ms"),
    ):
        values = np.array([s.data for s in listener.got[topic]])
        assert len(values) == stats[key]["count"], topic
        for q in (50, 90, 99):
            assert abs(np.percentile(values, q) - stats[key][f"p{q}"]) <= 0.05 * abs(stats[key][f"p{q}"]), (
                topic
            )
    proc_ms = np.array([s.data for s in listener.got["processing_time_ms"]])
    assert (proc_ms[4:8] >= 800).all() and (np.delete(proc_ms, range(4, 8)) < 800).all()

    # Foxglove: both clouds, one message each per scan
    assert len(fox.messages["/radar/points"]) == count and len(fox.messages["/radar/points/dense"]) == count
    assert fox.server_info is not None


def test_dropped_points_counted_per_scan_and_in_totals() -> None:
    from msdnet.runtime.frontends.live.node import NodeStats

    stats = NodeStats()
    stats.add_scan("1.000000000", {"points_in": 100, "dropped_nonfinite": 4, "dropped_outside_grid": 30})
    stats.add_scan("1.100000000", {"points_in": 90, "dropped_outside_grid": 10, "dropped_over_cap": 2})
    s = stats.summary()
    assert s["input_points"] == {
        "in": 194,
        "dropped_nonfinite": 4,
        "dropped_outside_grid": 40,
        "dropped_over_cap": 2,
        "dropped": 46,
    }
    assert [x["dropped_nonfinite"] for x in s["input_points_per_scan"]] == [4, 0]
    assert (
        "input points 194, dropped 46 (with NaN/Inf 4, outside the grid 40, over the voxel cap 2)"
        in stats.line()
    )


def _status_kib(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return -1


def test_100mb_pointcloud2_really_arrives_and_is_refused(vod_root, tmp_path) -> None:
    """A 104 MB PointCloud2 (6.5 M points, over the 5 M cap, its header true) sent reliably over
    loopback with large socket buffers reaches a node whose subscriber is reliable, which names it
    on stderr and serves the next scan; the node's peak resident memory is measured (printed with
    -s). (A best-effort subscriber loses it whole without a trace when the kernel caps the socket
    buffers below the message, net.core.rmem_max: see docs/live.md.)"""
    env = loopback_env(tmp_path, socket_buffer="256MiB")
    os.environ["CYCLONEDDS_URI"] = env["CYCLONEDDS_URI"]
    domain = DOMAIN + 3
    args = ["--domain-id", str(domain), "--threads", "1", "--provider", "cpu"]
    proc, _ = _start(env, [*args, "--input-reliability", "reliable"])  # best effort loses it whole
    collector = DenseCollector("/radar/points", domain)
    dds = Endpoints(domain)
    try:
        collector.wait_matched()
        writer = dds.writer(dds_topic("/radar/points"), reliable=True)
        from msdnet.runtime.frontends.live.publish import wait_matched

        wait_matched(writer.get_matched_subscriptions, "the node")
        time.sleep(0.3)
        before = _status_kib(proc.pid, "VmHWM")
        big = cloud_message(np.zeros((6_500_000, 4), np.float32), list("xyzw"), (1, 0), "radar")
        assert len(big.data) == 104_000_000
        start = time.monotonic()
        writer.write(big)
        del big
        from cyclonedds.util import duration

        acked = writer.wait_for_acks(duration(seconds=30))  # keep-last 1: not replaced first
        arrived = time.monotonic() - start
        time.sleep(1.5)  # the node takes it before the next scan (which would replace it: latest wins)
        c = read_cloud(_vod(vod_root)[0])
        writer.write(cloud_message(c.points, c.columns, (2, 0), "radar"))
        assert collector.wait_for(1, 60), "the scan after the 100 MB message was not served"
        seconds = time.monotonic() - start
        peak = _status_kib(proc.pid, "VmHWM")
        rss = _status_kib(proc.pid, "VmRSS")
    finally:
        collector.close()
        dds.close()
        out, err = _stop(proc)
    assert acked, "the 100 MB message was not acknowledged within 30 s"
    assert collector.received[0][0] == 2 * 10**9  # the small scan, served after the big one
    line = [x for x in err.splitlines() if "bad message" in x]
    assert len(line) == 1 and "6500000 points exceeds the cap of 5000000" in line[0], (out, err)
    assert "received 2, published 1, dropped 0, bad 1" in out
    print(
        f"\n100 MB PointCloud2: acknowledged {arrived:.1f} s after the send, refused; next scan served"
        f" {seconds:.1f} s after the send; node"
        f" peak RSS {before / 1024:.0f} MiB before -> {peak / 1024:.0f} MiB, RSS after {rss / 1024:.0f} MiB"
    )
    assert peak - before < 700 * 1024  # transient copies of the message (~5 x 104 MB measured), no more


def test_docs_list_every_parameter_with_its_default() -> None:
    from msdnet.runtime.frontends.live.params import PARAMS

    page = (Path(__file__).resolve().parents[1] / "docs" / "live.md").read_text(encoding="utf-8")
    rows = {line.split("|")[1].strip(" `"): line for line in page.splitlines() if line.startswith("| `")}
    for p in PARAMS:
        assert p.name in rows, f"docs/live.md has no row for {p.name}"
        default = {True: "true", False: "false"}.get(p.default, p.default) if p.kind == "bool" else p.default
        shown = '""' if default == "" else "[]" if default == [] else str(default)
        assert f"`{shown}`" in rows[p.name], f"docs/live.md: {p.name} default is not {shown}"
