"""``msdnet-infer BAG --topic T --out OUT_BAG``: densify the PointCloud2 messages of a ROS bag.

Every ``sensor_msgs/PointCloud2`` on topic ``T`` goes through the pipeline (bags are read and
written by ``io/rosbag``); the output is a ROS 2 bag holding every input message unchanged (ROS 1
messages re-encoded as CDR, their content unchanged) plus ``T/dense``: one PointCloud2 per
densified message with float32 fields ``x y z confidence`` (point_step 16, little-endian, height
1), the input message's header (stamp and frame_id) and bag timestamp. Storage: the input's, or
``--bag-storage``; a ROS 1 input is written as MCAP (the ROS 2 default since Iron) unless
``--bag-storage`` says otherwise.

Fields are mapped as ``io/rosbag`` describes (``--field model_column=msg_field``). A field
missing from the first message is a one-line error naming the topic and the field; a later
message that cannot be read or run is counted and reported in the summary, and the rest go on.

Output: written under a temporary name next to ``OUT_BAG`` (``io.atomic.temp_name``, pid-tagged:
the next run removes a killed run's) and renamed when complete; an existing ``OUT_BAG`` is
refused, and so is a place that cannot be written, before any work (``io/bag_guards``). A write
that fails (read-only, disk full, in either storage) is one line naming ``OUT_BAG`` and the
cause, with nothing left behind. A ``metadata.yaml`` that is broken or not a rosbag2 one is one
line naming the bag.
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

from msdnet.runtime.engine.pointcloud import DROP_REASONS
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.densify import DensifyOptions, densify
from msdnet.runtime.io.atomic import temp_name, write_error
from msdnet.runtime.io.bag_guards import bag_write_error, prepare_bag_out, storage_of
from msdnet.runtime.io.files import DENSE_COLUMNS
from msdnet.runtime.io.rosbag import (
    POINTCLOUD2,
    ROS1_DEFAULT_STORAGE,
    STORAGES,
    _rosbags,
    make_pointcloud2,
    message_cloud,
    parse_field_map,
    resolve_fields,
)

DENSE_SUFFIX = "/dense"  # output topic = input topic + this


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
    options: DensifyOptions,
    log_frame: Callable[..., None] | None = None,
    echo: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Densify ``topic`` of one bag into the ROS 2 bag ``out`` (module docstring); -> one row per
    topic message as the file mode counts files (file, points_in, points_out, seconds, notes or
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
                row, dense = _run_message(
                    pipe, reader, raw, mapping, options, label, ros2, log_frame, len(rows)
                )
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
    options: DensifyOptions,
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
        row.update(points_in=len(cloud), dropped_nonfinite=cloud.dropped_nonfinite)
        res = densify(pipe, cloud, options)
        row.update({k: res.stats[k] for k in DROP_REASONS})  # every row not used, by reason
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
    options: DensifyOptions,
) -> list[dict[str, Any]]:
    """``msdnet-infer --topic``: one Pipeline, :func:`run_bag`, and the ``--rerun`` recording."""
    import click

    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.io.rerun_log import recording

    _rosbags()  # the missing-extra message before anything else
    pipe = Pipeline(artifact, provider=provider, threads=threads)
    with recording(rerun) as log:
        frame = None if log is None else log.frame
        return run_bag(pipe, inputs, out, topic, field_specs, storage, options, frame, click.echo)
