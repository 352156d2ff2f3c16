"""``msdnet-infer BAG --topic``: ROS 1 and ROS 2 (sqlite3, MCAP) bags built with ``rosbags`` from
real VoD radar scans and simulated scans come back as ROS 2 bags holding every input message
unchanged plus ``<topic>/dense``, whose points equal the file mode's for the same frames and seed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from msdnet.runtime.frontends.infer.cli import main
from msdnet.runtime.io.files import DENSE_COLUMNS, VOD_RADAR_COLUMNS, read_cloud
from msdnet.runtime.sim.sequence import SequenceSim

rosbags = pytest.importorskip("rosbags", reason="the [ros] extra (CI installs it)")
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from msdnet.runtime.io.rosbag import POINTCLOUD2, files_to_bag, make_pointcloud2  # noqa: E402

TOPIC = "/radar/points"
RUN = ["--steps", "3", "--threads", "1", "--seed", "5", "--provider", "cpu"]
STAMP0 = 1_700_000_000  # seconds
FRAME_ID = "radar_link"


@pytest.fixture(scope="module")
def frames(vod_root, tmp_path_factory) -> list[Path]:
    """Three real VoD scans and two simulated scans, as files the file mode reads (N, 7)."""
    vod = sorted((vod_root / "radar" / "training" / "velodyne").glob("*.bin"))
    folder = tmp_path_factory.mktemp("sim")
    sim = SequenceSim(11, 0, 2)
    for f in range(2):
        np.save(folder / f"sim{f}.npy", sim.frame(f).radar)  # (M, 7) VoD radar columns
    return [*vod, *sorted(folder.glob("*.npy"))]


@pytest.fixture(scope="module")
def file_mode(frames, tmp_path_factory) -> list[np.ndarray]:
    """(M, 4) [x, y, z, confidence] per frame, written by the file mode."""
    out = tmp_path_factory.mktemp("files")
    r = CliRunner().invoke(main, [*map(str, frames), "--out", str(out), *RUN])
    assert r.exit_code == 0, r.output
    return [read_cloud(out / f"{f.stem}.npy", columns=DENSE_COLUMNS).points for f in frames]


def _scan(path: Path) -> np.ndarray:
    return read_cloud(path).select(VOD_RADAR_COLUMNS).points  # (N, 7)


def write_bag(path: Path, kind: str, scans: list[np.ndarray], names=VOD_RADAR_COLUMNS, extra=True) -> Path:
    """A bag with ``TOPIC`` (one PointCloud2 per scan, 0.1 s apart) and, with ``extra``, a
    std_msgs/String on /note between the scans; kind: ros1, sqlite3 or mcap."""
    ros1 = kind == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:
        path = path.with_suffix(".bag")
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
        writer = Writer2(path, version=9, storage_plugin=plugin)
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    with writer:
        pc = writer.add_connection(TOPIC, POINTCLOUD2, typestore=store)
        note = writer.add_connection("/note", "std_msgs/msg/String", typestore=store)
        for i, scan in enumerate(scans):
            stamp = (STAMP0 + i // 10, (i % 10) * 100_000_000 + 7)
            ns = stamp[0] * 10**9 + stamp[1]
            msg = make_pointcloud2(store, scan, names, stamp, FRAME_ID)
            writer.write(pc, ns + 1000, bytes(serialize(msg, POINTCLOUD2)))
            if extra:
                text = store.types["std_msgs/msg/String"](f"frame {i}")
                writer.write(note, ns + 2000, bytes(serialize(text, "std_msgs/msg/String")))
    return path


def read_bag(path: Path) -> tuple[str | None, dict[str, list[tuple[int, bytes, object]]]]:
    """-> (storage of a ROS 2 bag, {topic: [(bag time, raw, message), ...]})."""
    storage = None
    if path.is_dir():
        storage = "mcap" if list(path.glob("*.mcap")) else "sqlite3" if list(path.glob("*.db3")) else "?"
    topics: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, t, raw in reader.messages():
            topics.setdefault(conn.topic, []).append((t, bytes(raw), reader.deserialize(raw, conn.msgtype)))
    return storage, topics


def _dense_points(msg) -> np.ndarray:
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        (n, 4 * i, 7, 1) for i, n in enumerate(DENSE_COLUMNS)
    ]
    assert (msg.height, msg.point_step, msg.is_bigendian) == (1, 16, False)
    return np.frombuffer(bytes(msg.data), "<f4").reshape(msg.width, 4)


def _infer(*args) -> object:
    argv = [str(a) for a in args]  # --provider cpu unless given: outputs are compared with cpu's bytes
    return CliRunner().invoke(main, argv if "--provider" in argv else [*argv, "--provider", "cpu"])


@pytest.mark.parametrize(
    ("kind", "storage_arg", "storage_out"),
    [
        ("ros1", None, "mcap"),
        ("sqlite3", None, "sqlite3"),
        ("mcap", None, "mcap"),
        ("sqlite3", "mcap", "mcap"),
    ],
)
def test_bag_round_trip_equals_file_mode(frames, file_mode, tmp_path, kind, storage_arg, storage_out):
    bag = write_bag(tmp_path / "in", kind, [_scan(f) for f in frames])
    out = tmp_path / "out"
    extra = [] if storage_arg is None else ["--bag-storage", storage_arg]
    r = _infer(bag, "--topic", TOPIC, "--out", out, *RUN, *extra)
    assert r.exit_code == 0, r.output
    assert f"messages: {len(frames)} ok, 0 failed" in r.output
    assert ("ROS 1 input: writing a ROS 2 bag in mcap storage" in r.output) == (kind == "ros1")
    storage, got = read_bag(out)
    _, src = read_bag(bag)
    assert storage == storage_out
    assert sorted(got) == sorted([TOPIC, "/note", TOPIC + "/dense"])
    for topic in (TOPIC, "/note"):  # every input message, same times, same content
        assert [t for t, _, _ in got[topic]] == [t for t, _, _ in src[topic]]
        if kind != "ros1":
            assert [raw for _, raw, _ in got[topic]] == [raw for _, raw, _ in src[topic]]
    assert [m.data for _, _, m in got["/note"]] == [f"frame {i}" for i in range(len(frames))]
    for (_, _, a), (_, _, b) in zip(got[TOPIC], src[TOPIC], strict=True):
        assert bytes(a.data) == bytes(b.data) and a.header.stamp == b.header.stamp
    dense = got[TOPIC + "/dense"]
    assert len(dense) == len(frames)
    for (t, _, msg), (t_in, _, m_in), expected in zip(dense, src[TOPIC], file_mode, strict=True):
        assert t == t_in
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (
            m_in.header.stamp.sec,
            m_in.header.stamp.nanosec,
        )
        assert msg.header.frame_id == FRAME_ID
        assert len(expected) > 0
        np.testing.assert_array_equal(_dense_points(msg), expected)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_field_override_and_missing_field(frames, file_mode, tmp_path):
    names = ("x", "y", "z", "RCS_dBsm", "v_r", "vel_comp", "time")
    bag = write_bag(tmp_path / "in", "mcap", [_scan(f) for f in frames[:2]], names=names, extra=False)
    r = _infer(bag, "--topic", TOPIC, "--out", tmp_path / "bad", *RUN)
    assert r.exit_code == 2
    assert r.output.strip().splitlines() == [
        f"error: {TOPIC}: PointCloud2 has no field 'rcs' for model column 'rcs' "
        f"(fields: {' '.join(names)}); map one with --field rcs=FIELD"
    ]
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "out"
    r = _infer(
        bag,
        "--topic",
        TOPIC,
        "--out",
        out,
        "--field",
        "rcs=RCS_dBsm",
        "--field",
        "v_r_compensated=vel_comp",
        *RUN,
    )
    assert r.exit_code == 0, r.output
    dense = read_bag(out)[1][TOPIC + "/dense"]
    for (_, _, msg), expected in zip(dense, file_mode[:2], strict=True):
        np.testing.assert_array_equal(_dense_points(msg), expected)
    r = _infer(bag, "--topic", TOPIC, "--out", tmp_path / "x", "--field", "speed=vel_comp", *RUN)
    assert r.exit_code == 2 and "--field: the model has no column 'speed'" in r.output


def test_bad_message_is_counted_and_the_rest_go_on(frames, file_mode, tmp_path):
    bag = write_bag(tmp_path / "in", "sqlite3", [_scan(f) for f in frames[:3]])
    # cut message 1's point data short: it cannot be read, messages 0 and 2 still are
    store = get_typestore(Stores.ROS2_HUMBLE)
    _, src = read_bag(bag)
    broken = tmp_path / "broken"
    with Writer2(broken, version=9) as w:
        pc = w.add_connection(TOPIC, POINTCLOUD2, typestore=store)
        for i, (t, _, msg) in enumerate(src[TOPIC]):
            if i == 1:
                msg.data = msg.data[:-5]
            w.write(pc, t, bytes(store.serialize_cdr(msg, POINTCLOUD2)))
    out = tmp_path / "out"
    r = _infer(broken, "--topic", TOPIC, "--out", out, *RUN)
    assert r.exit_code == 1, r.output
    assert "messages: 2 ok, 1 failed" in r.output
    assert f"FAILED {broken}: {TOPIC} message 1 at {src[TOPIC][1][0]} ns: data has" in r.output
    got = read_bag(out)[1]
    assert len(got[TOPIC]) == 3 and len(got[TOPIC + "/dense"]) == 2
    for (t, _, msg), i in zip(got[TOPIC + "/dense"], (0, 2), strict=True):
        assert t == src[TOPIC][i][0]
        np.testing.assert_array_equal(_dense_points(msg), file_mode[i])


def test_bag_argument_errors(frames, tmp_path):
    bag = write_bag(tmp_path / "in", "mcap", [_scan(frames[0])])
    r = _infer(bag, "--topic", "/lidar", "--out", tmp_path / "o", *RUN)
    assert r.exit_code == 2
    assert (
        f"error: {bag}: no topic '/lidar' (topics: /note (std_msgs/msg/String), {TOPIC} ({POINTCLOUD2}))"
        in r.output
    )
    r = _infer(bag, "--topic", "/note", "--out", tmp_path / "o", *RUN)
    assert r.exit_code == 2 and f"messages are std_msgs/msg/String, not {POINTCLOUD2}" in r.output
    (tmp_path / "taken").mkdir()
    r = _infer(bag, "--topic", TOPIC, "--out", tmp_path / "taken", *RUN)
    assert r.exit_code == 2 and "already exists" in r.output
    r = _infer(frames[0], "--topic", TOPIC, "--out", tmp_path / "o", *RUN)
    assert r.exit_code == 2 and "not a ROS 1 bag (.bag file) or a ROS 2 bag" in r.output
    r = _infer(frames[0], "--out", tmp_path / "o", "--field", "rcs=a", *RUN)
    assert r.exit_code == 2 and "--field/--bag-storage: only apply with --topic" in r.output


def test_files_to_bag_then_topic_equals_file_mode(frames, file_mode, tmp_path):
    bag = files_to_bag(frames, tmp_path / "bag", storage="sqlite3", frame_id="radar", hz=10.0)
    r = _infer(bag, "--topic", "/radar/points", "--out", tmp_path / "out", *RUN)
    assert r.exit_code == 0, r.output
    src = read_bag(bag)[1]["/radar/points"]
    dense = read_bag(tmp_path / "out")[1]["/radar/points/dense"]
    assert [t for t, _, _ in src] == [1_700_000_000 * 10**9 + i * 10**8 for i in range(len(frames))]
    for (t, _, msg), (t_in, _, _), expected in zip(dense, src, file_mode, strict=True):
        assert t == t_in and msg.header.frame_id == "radar"
        np.testing.assert_array_equal(_dense_points(msg), expected)
