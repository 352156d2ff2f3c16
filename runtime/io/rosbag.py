"""ROS bags and PointCloud2 messages, with the pure-Python ``rosbags`` library (``[ros]`` extra).

Reads ROS 1 bags (one ``.bag`` file) and ROS 2 bags (a folder with ``metadata.yaml``, sqlite3 or
MCAP storage) with no ROS install. Used by ``msdnet-infer BAG --topic`` (``frontends/infer/bag``),
``msdnet-data pair`` (``io/pairing``) and ``msdnet-node`` (``frontends/live/messages``).

Field mapping (:func:`parse_field_map`, :func:`resolve_fields`): each model column (manifest
``input.columns``, e.g. ``x y z rcs v_r_compensated``) reads the message field of the same
canonical name (``RCS`` -> ``rcs``); ``--field model_column=msg_field`` overrides one. A missing
field is one line naming the topic and the field; two fields of one name (or of one canonical
name feeding a column) are refused, naming the topic and the field. :func:`message_cloud` turns
one serialized message into a PointCloud: rows with a non-finite value in a model column are
dropped (as the file readers drop them), and a message of more than ``io.files.MAX_POINTS``
points is refused as a file that size is, naming the message. A message must hold exactly what
its header states (:func:`check_pointcloud2_size`, the readers' ``io.files.check_held`` rule):
``data`` of other than ``height * row_step`` bytes is refused, never cut to the stated points.
:func:`make_pointcloud2` builds a
float32 PointCloud2 (point_step 4 C, little-endian, height 1); :func:`files_to_bag` writes
point-cloud files as a ROS 2 bag, for trying ``--topic`` without a recorded bag.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.engine.pointcloud import canonical_column
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.files import MAX_POINTS, check_held, cloud_from_array

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
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


def check_pointcloud2_size(msg: Any) -> int:
    """The bytes of one row of ``msg`` after checking that ``data`` holds exactly ``height`` rows
    of ``row_step`` bytes, each with room for ``width`` points of ``point_step`` bytes and less
    padding than one more point (a height-1 message whose ``row_step`` is below that uses
    ``width * point_step``). ValueError otherwise: a message that says less than it holds is
    not cut to what it says."""
    step, width, height = int(msg.point_step), int(msg.width), int(msg.height)
    row = int(msg.row_step)
    if height == 1 and row < width * step:
        row = width * step
    size = len(msg.data)
    if width * step > row or size < height * row:
        raise ValueError(f"data has {size} bytes, {height} rows of {width} x {step}-byte points need more")
    if step and row - width * step >= step:
        raise ValueError(
            f"PointCloud2 row_step {row} bytes holds {row // step} points of {step} bytes, width says "
            f"{width}; refusing to cut it to the stated points"
        )
    try:
        check_held(None, f"bytes ({width * height} points: {height} x row_step {row})", height * row, size)
    except MsdnetError as err:
        raise ValueError(f"PointCloud2 {err.cause}; refusing to cut it to the stated points") from None
    return row


def pointcloud2_to_array(
    msg: Any, fields: Sequence[Any], label: str = "PointCloud2", max_points: int = MAX_POINTS
) -> np.ndarray:
    """PointCloud2 ``msg`` -> (N, len(fields)) float32, N = height * width, row padding skipped;
    MsdnetError naming ``label`` when N exceeds ``max_points`` (the file readers' cap),
    ValueError when ``data`` holds more or less than the header states
    (:func:`check_pointcloud2_size`)."""
    order = ">" if msg.is_bigendian else "<"
    step, width, height = int(msg.point_step), int(msg.width), int(msg.height)
    if width * height > max_points:
        raise MsdnetError(label, f"{width * height} points exceeds the cap of {max_points} per scan")
    row = check_pointcloud2_size(msg)
    data = np.asarray(msg.data, dtype=np.uint8)
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
