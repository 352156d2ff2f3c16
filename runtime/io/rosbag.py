"""``msdnet-infer BAG --topic T --out OUT_BAG``: densify the PointCloud2 messages of a ROS bag.

Reads ROS 1 bags (one ``.bag`` file) and ROS 2 bags (a folder with ``metadata.yaml``, sqlite3 or
MCAP storage) with the pure-Python ``rosbags`` library (``[ros]`` extra; no ROS install). Every
``sensor_msgs/PointCloud2`` on topic ``T`` goes through the pipeline; the output is a ROS 2 bag
holding every input message unchanged (ROS 1 messages re-encoded as CDR, their content
unchanged) plus ``T/dense``: one PointCloud2 per densified message with float32 fields
``x y z confidence`` (point_step 16, little-endian, height 1), the input message's header
(stamp and frame_id) and bag timestamp. Storage: the input's, or ``--bag-storage``; a ROS 1
input is written as MCAP (the ROS 2 default since Iron) unless ``--bag-storage`` says otherwise.

Field mapping: each model column (manifest ``input.columns``, e.g. ``x y z rcs
v_r_compensated``) reads the message field of the same canonical name (``RCS`` -> ``rcs``);
``--field model_column=msg_field`` overrides one. A field missing from the first message is a
one-line error naming the topic and the field; a later message that cannot be read or run is
counted and reported in the summary, and the rest go on. Rows with a non-finite value in a model
column are dropped (as the file readers drop them). Two fields of one name (or of one canonical
name feeding a column) are refused, naming the topic and the field; a message of more than
``io.MAX_POINTS`` points is refused as a file that size is, naming the message.

Output: written under a temporary name next to ``OUT_BAG`` (``io.temp_name``, pid-tagged: the
next run removes a killed run's) and renamed when complete; an existing ``OUT_BAG`` is refused,
and so is a place that cannot be written, before any work. A write that fails (read-only, disk
full, in either storage) is one line naming ``OUT_BAG`` and the cause, with nothing left behind.
A ``metadata.yaml`` that is broken or not a rosbag2 one is one line naming the bag.
"""

from __future__ import annotations

import shutil
import sqlite3
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msdnet.runtime.engine.pointcloud import canonical_column
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.infer.worker import densify
from msdnet.runtime.io.bag_guards import bag_write_error, prepare_bag_out, storage_of
from msdnet.runtime.io.files import DENSE_COLUMNS, MAX_POINTS, cloud_from_array, temp_name, write_error

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
DENSE_SUFFIX = "/dense"  # output topic = input topic + this
STORAGES = ("sqlite3", "mcap")
ROS1_DEFAULT_STORAGE = "mcap"  # ROS 2's default storage since Iron
# sensor_msgs/PointField datatype -> numpy scalar type (byte order added per message)
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
FLOAT32 = 7


def _rosbags() -> Any:
    try:
        import rosbags  # noqa: F401
    except ImportError:
        raise MsdnetError("--topic", "needs the rosbags package: pip install 'msdnet[ros]'") from None
    from rosbags import highlevel, rosbag2, typesys

    return highlevel, rosbag2, typesys


def parse_field_map(specs: Sequence[str], columns: Sequence[str]) -> dict[str, str]:
    """``("rcs=RCS_dB", ...)`` -> {model column: message field}; MsdnetError on a bad entry."""
    mapping: dict[str, str] = {}
    for spec in specs:
        col, sep, field = spec.partition("=")
        col, field = canonical_column(col), field.strip()
        if not sep or not col or not field:
            raise MsdnetError("--field", f"expected model_column=msg_field, got {spec!r}")
        if col not in columns:
            raise MsdnetError("--field", f"the model has no column {col!r} (columns: {' '.join(columns)})")
        mapping[col] = field
    return mapping


def resolve_fields(msg: Any, columns: Sequence[str], mapping: dict[str, str], topic: str) -> list[Any]:
    """The PointField of ``msg`` feeding each model column; MsdnetError naming topic and field."""
    names = [f.name for f in msg.fields]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise MsdnetError(
            topic, f"PointCloud2 has two fields named {twice[0]!r}: which one is meant is unknown"
        )
    by_name = {f.name: f for f in msg.fields}
    by_canon: dict[str, list[Any]] = {}
    for f in msg.fields:
        by_canon.setdefault(canonical_column(f.name), []).append(f)
    have = " ".join(n if n.isprintable() and n.split() == [n] else repr(n) for n in by_name) or "none"
    picked = []
    for col in columns:
        same = by_canon.get(col, [])
        if col not in mapping and len(same) > 1:
            raise MsdnetError(
                topic,
                f"PointCloud2 fields {' and '.join(repr(f.name) for f in same)} both match model column "
                f"{col!r}; pick one with --field {col}=FIELD",
            )
        field = by_name.get(mapping[col]) if col in mapping else (same[0] if same else None)
        if field is None:
            name = mapping.get(col, col)
            raise MsdnetError(
                topic,
                f"PointCloud2 has no field {name!r} for model column {col!r} (fields: {have}); "
                f"map one with --field {col}=FIELD",
            )
        if field.count != 1 or field.datatype not in POINTFIELD_TYPES:
            raise MsdnetError(topic, f"field {field.name!r}: datatype {field.datatype} count {field.count}")
        picked.append(field)
    return picked


def pointcloud2_to_array(
    msg: Any, fields: Sequence[Any], label: str = "PointCloud2", max_points: int = MAX_POINTS
) -> np.ndarray:
    """PointCloud2 ``msg`` -> (N, len(fields)) float32, N = height * width, row padding skipped;
    MsdnetError naming ``label`` when N exceeds ``max_points`` (the file readers' cap)."""
    order = ">" if msg.is_bigendian else "<"
    step, width, height = int(msg.point_step), int(msg.width), int(msg.height)
    if width * height > max_points:
        raise MsdnetError(label, f"{width * height} points exceeds the cap of {max_points} per scan")
    row = int(msg.row_step) if height > 1 else width * step
    data = np.asarray(msg.data, dtype=np.uint8)
    if width * step > row or data.size < height * row:
        raise ValueError(
            f"data has {data.size} bytes, {height} rows of {width} x {step}-byte points need more"
        )
    for f in fields:
        if f.offset + np.dtype(POINTFIELD_TYPES[f.datatype]).itemsize > step:
            raise ValueError(f"field {f.name!r} at offset {f.offset} overruns point_step {step}")
    dtype = np.dtype(
        {
            "names": [f"c{i}" for i in range(len(fields))],
            "formats": [order + POINTFIELD_TYPES[f.datatype] for f in fields],
            "offsets": [int(f.offset) for f in fields],
            "itemsize": step,
        }
    )
    rows = data[: height * row].reshape(height, row)[:, : width * step]
    packed = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    out = np.empty((packed.shape[0], len(fields)), np.float32)
    for i in range(len(fields)):
        out[:, i] = packed[f"c{i}"]
    return out


def message_cloud(
    deserialize: Callable[[bytes, str], Any],
    raw: bytes,
    columns: Sequence[str],
    mapping: dict[str, str],
    label: str,
) -> tuple[Any, Any]:
    """Serialized PointCloud2 ``raw`` -> (message, PointCloud of ``columns``); any bad content
    (undecodable bytes, missing or duplicate fields, a short buffer, over the point cap) is one
    MsdnetError naming ``label``. ``deserialize(raw, msgtype)``: the reader's or a typestore's."""
    try:
        msg = deserialize(raw, POINTCLOUD2)
    except Exception as err:  # struct, index, unicode errors from a broken CDR / ROS 1 buffer
        cause = " ".join(str(err).split())[:160] or type(err).__name__
        raise MsdnetError(label, f"undecodable PointCloud2 ({type(err).__name__}: {cause})") from None
    fields = resolve_fields(msg, columns, mapping, label)
    try:
        values = pointcloud2_to_array(msg, fields, label)
    except (ValueError, TypeError, OverflowError) as err:
        raise MsdnetError(label, " ".join(str(err).split())[:200]) from None
    return msg, cloud_from_array(label, values, tuple(columns))


def make_pointcloud2(store: Any, points: np.ndarray, names: Sequence[str], stamp: Any, frame_id: str) -> Any:
    """(N, C) values -> PointCloud2 of ``store`` (a rosbags typestore, ROS 1 or 2) with float32
    fields ``names`` (point_step 4 C, little-endian, height 1); ``stamp`` = (sec, nanosec)."""
    types = store.types
    pts = np.ascontiguousarray(points, dtype="<f4")
    fields = [types["sensor_msgs/msg/PointField"](n, 4 * i, FLOAT32, 1) for i, n in enumerate(names)]
    time_ = types["builtin_interfaces/msg/Time"](*stamp)
    header_t = types["std_msgs/msg/Header"]
    extra = {"seq": 0} if "seq" in header_t.__dataclass_fields__ else {}  # ROS 1 headers count
    header = header_t(stamp=time_, frame_id=frame_id, **extra)
    data = pts.reshape(-1).view(np.uint8)
    step = 4 * len(names)
    return types[POINTCLOUD2](header, 1, len(pts), fields, False, step, step * len(pts), data, True)


def _check_paths(inputs: Sequence[Path], out: Path) -> tuple[Path, bool]:
    """-> (bag, is ROS 2); MsdnetError for anything but one readable bag and a free --out."""
    if len(inputs) != 1:
        raise MsdnetError(" ".join(map(str, inputs)), "--topic takes exactly one bag")
    bag = inputs[0]
    if bag.is_file() and bag.suffix == ".bag":
        is2 = False
    elif bag.is_dir() and (bag / "metadata.yaml").is_file():
        is2 = True
    else:
        raise MsdnetError(bag, "not a ROS 1 bag (.bag file) or a ROS 2 bag (folder with metadata.yaml)")
    if out.exists():
        raise MsdnetError(out, "already exists; remove it or choose another --out (a bag is written whole)")
    return bag, is2


def run_bag(
    pipe: Any,
    inputs: Sequence[Path],
    out: Path,
    topic: str,
    field_specs: Sequence[str],
    storage: str | None,
    opts: dict[str, Any],
    log_frame: Callable[..., None] | None = None,
    echo: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Densify ``topic`` of one bag into the ROS 2 bag ``out`` (module docstring); -> one row per
    topic message as ``infer_cli`` counts files (file, points_in, points_out, seconds, notes or
    error). ``log_frame(index, label, radar_xyz, dense_xyz, confidence, stamp_ns=...)`` is called
    per densified message (``--rerun``)."""
    highlevel, rosbag2, typesys = _rosbags()
    from rosbags.convert.converter import create_connections_converters

    bag, is2 = _check_paths(inputs, out)
    mapping = parse_field_map(field_specs, pipe.columns)
    if storage is None:
        storage = storage_of(bag) if is2 else ROS1_DEFAULT_STORAGE
        if not is2:
            echo(f"ROS 1 input: writing a ROS 2 bag in {storage} storage (--bag-storage sqlite3|mcap)")
    if storage not in STORAGES:
        raise MsdnetError(bag, f"storage {storage!r} cannot be written (--bag-storage {'|'.join(STORAGES)})")
    ros2 = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    dense_topic = topic.rstrip("/") + DENSE_SUFFIX
    prepare_bag_out(out)
    try:
        reader = highlevel.AnyReader([bag], default_typestore=ros2)
        reader.open()
    except Exception as err:
        raise MsdnetError(bag, f"unreadable bag: {' '.join(str(err).split())[:200]}") from None
    tmp = out.parent / temp_name(out.name)  # removed by the next run's clean_stale_temps if killed
    try:
        tmp.mkdir()
    except OSError as err:
        reader.close()
        raise write_error(out, err) from None
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            topics = ", ".join(f"{t} ({i.msgtype})" for t, i in reader.topics.items()) or "none"
            raise MsdnetError(bag, f"no topic {topic!r} (topics: {topics})")
        if any(c.msgtype != POINTCLOUD2 for c in conns):
            raise MsdnetError(topic, f"messages are {conns[0].msgtype}, not {POINTCLOUD2}")
        if any(c.topic == dense_topic for c in reader.connections):
            raise MsdnetError(dense_topic, "the input bag already has this output topic")
        first = next(reader.messages(connections=conns), None)
        if first is None:
            raise MsdnetError(topic, "no messages on the topic")
        resolve_fields(reader.deserialize(first[2], POINTCLOUD2), pipe.columns, mapping, topic)
        plugin = {"sqlite3": rosbag2.StoragePlugin.SQLITE3, "mcap": rosbag2.StoragePlugin.MCAP}[storage]
        writer = rosbag2.Writer(tmp / out.name, version=9, storage_plugin=plugin)
        with writer:
            connmap, convmap = create_connections_converters(reader.connections, None, reader, writer)
            dense_conn = writer.add_connection(dense_topic, POINTCLOUD2, typestore=ros2)
            total = sum(c.msgcount for c in conns)
            rows: list[dict[str, Any]] = []
            bar = tqdm(total=total, unit="msg", desc="msdnet-infer", disable=None)
            for conn, stamp, raw in reader.messages():
                writer.write(connmap[(conn.id, conn.owner)], stamp, convmap[conn.msgtype](raw))
                if conn.topic != topic:
                    continue
                label = f"{bag}: {topic} message {len(rows)} at {stamp} ns"
                row, dense = _run_message(pipe, reader, raw, mapping, opts, label, ros2, log_frame, len(rows))
                if dense is not None:
                    writer.write(dense_conn, stamp, ros2.serialize_cdr(dense, POINTCLOUD2))
                rows.append(row)
                bar.update()
            bar.close()
        (tmp / out.name).rename(out)
    except (OSError, sqlite3.Error, rosbag2.WriterError) as err:  # disk full, read-only: one line
        raise bag_write_error(out, err) from None
    finally:
        reader.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


def _run_message(
    pipe: Any,
    reader: Any,
    raw: bytes,
    mapping: dict[str, str],
    opts: dict[str, Any],
    label: str,
    store: Any,
    log_frame: Callable[..., None] | None,
    index: int,
) -> tuple[dict[str, Any], Any]:
    """One topic message -> (summary row, dense PointCloud2 or None); never raises."""
    row: dict[str, Any] = {"file": label, "points_in": 0, "points_out": 0, "seconds": 0.0}
    try:
        start = time.perf_counter()
        msg, cloud = message_cloud(reader.deserialize, raw, pipe.columns, mapping, label)
        row.update(points_in=len(cloud), dropped=cloud.dropped_nonfinite)
        res = densify(pipe, cloud, opts)
        dense = np.concatenate([res.points, res.confidence[:, None]], axis=1)  # (M, 4)
        stamp = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        out = make_pointcloud2(store, dense, DENSE_COLUMNS, stamp, msg.header.frame_id)
        row.update(points_out=len(res.points), notes=list(res.notes))
        row["seconds"] = time.perf_counter() - start
        if log_frame is not None:
            ns = stamp[0] * 1_000_000_000 + stamp[1]
            log_frame(index, label, cloud.xyz, res.points, res.confidence, stamp_ns=ns)
        return row, out
    except MsdnetError as err:
        row["error"] = f"{label}: {err.cause}"
    except Exception as err:  # one bad message must not stop the bag
        row["error"] = f"{label}: {type(err).__name__}: {' '.join(str(err).split())[:200]}"
    return row, None


def bag_mode(
    artifact: Any,
    provider: str,
    threads: int | None,
    inputs: Sequence[Path],
    out: Path,
    topic: str,
    field_specs: Sequence[str],
    storage: str | None,
    rerun: Path | None,
    opts: dict[str, Any],
) -> list[dict[str, Any]]:
    """``msdnet-infer --topic``: one Pipeline, :func:`run_bag`, and the ``--rerun`` recording."""
    import click

    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.io.rerun_log import recording

    _rosbags()  # the missing-extra message before anything else
    pipe = Pipeline(artifact, provider=provider, threads=threads)
    with recording(rerun) as log:
        frame = None if log is None else log.frame
        return run_bag(pipe, inputs, out, topic, field_specs, storage, opts, frame, click.echo)


def files_to_bag(
    inputs: str | Path | Sequence[str | Path],
    out: str | Path,
    topic: str = "/radar/points",
    storage: str = "mcap",
    frame_id: str = "radar",
    hz: float = 10.0,
    start_ns: int = 1_700_000_000 * 10**9,
) -> Path:
    """Write point-cloud files (a folder's files, sorted, or a list; any ``read_cloud`` format)
    as a ROS 2 bag: one float32 PointCloud2 per file on ``topic``, all columns, ``hz`` apart
    from ``start_ns`` (header stamp = bag time). For trying ``--topic`` without a recorded bag."""
    from msdnet.runtime.io.files import READ_FORMATS, read_cloud

    _, rosbag2, typesys = _rosbags()
    items = [Path(inputs)] if isinstance(inputs, (str, Path)) else [Path(p) for p in inputs]
    files = [f for p in items for f in (sorted(p.iterdir()) if p.is_dir() else [p])]
    files = [f for f in files if f.suffix.lower() in READ_FORMATS]
    store = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    plugin = {"sqlite3": rosbag2.StoragePlugin.SQLITE3, "mcap": rosbag2.StoragePlugin.MCAP}[storage]
    out = Path(out)
    with rosbag2.Writer(out, version=9, storage_plugin=plugin) as bag:
        conn = bag.add_connection(topic, POINTCLOUD2, typestore=store)
        for i, path in enumerate(files):
            cloud = read_cloud(path)
            ns = start_ns + round(i * 1e9 / hz)
            msg = make_pointcloud2(store, cloud.points, cloud.columns, divmod(ns, 10**9), frame_id)
            bag.write(conn, ns, bytes(store.serialize_cdr(msg, POINTCLOUD2)))
    return out
