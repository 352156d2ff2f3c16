"""PointCloud2 IDL messages <-> arrays, through the bag mode's code (``runtime/io/rosbag``).

``io.rosbag`` reads a PointCloud2 by field name (``--field`` overrides) and writes the dense
output (float32 ``x y z confidence``, point_step 16, little-endian, height 1); the same functions
serve the live node: :data:`IDL_STORE` makes ``io.rosbag.make_pointcloud2`` build the IDL structs
of :mod:`msdnet.runtime.frontends.live.idl`, and :func:`message_cloud` feeds them to
``io.rosbag.pointcloud2_to_array``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np

from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.live.idl import Header, PointCloud2, PointField, Time
from msdnet.runtime.io.files import DENSE_COLUMNS, MAX_POINTS, cloud_from_array
from msdnet.runtime.io.rosbag import POINTCLOUD2, make_pointcloud2, pointcloud2_to_array, resolve_fields


def _pointcloud2(*args: Any) -> PointCloud2:
    """``io.rosbag``'s positional PointCloud2 arguments, ``data`` (a uint8 array) as bytes."""
    values = list(args)
    values[7] = np.ascontiguousarray(values[7], dtype=np.uint8).tobytes()
    return PointCloud2(*values)


IDL_STORE = SimpleNamespace(  # a stand-in for a rosbags typestore: the IDL struct constructors
    types={
        "sensor_msgs/msg/PointField": PointField,
        "builtin_interfaces/msg/Time": Time,
        "std_msgs/msg/Header": Header,
        POINTCLOUD2: _pointcloud2,
    }
)


def stamp_of(msg: PointCloud2) -> tuple[int, int]:
    """(sec, nanosec) of the message's header."""
    return int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)


def cloud_message(
    points: np.ndarray, names: Sequence[str], stamp: tuple[int, int], frame_id: str
) -> PointCloud2:
    """(N, C) values -> PointCloud2 with float32 fields ``names`` (point_step 4 C, height 1)."""
    return make_pointcloud2(IDL_STORE, points, names, stamp, frame_id)


def dense_message(points: np.ndarray, confidence: np.ndarray, header: Header) -> PointCloud2:
    """points (M, 3), confidence (M,) -> the ``/dense`` PointCloud2 (``x y z confidence``) with
    the input's stamp and frame_id."""
    dense = np.concatenate([points, confidence[:, None]], axis=1)  # (M, 4)
    stamp = (int(header.stamp.sec), int(header.stamp.nanosec))
    return make_pointcloud2(IDL_STORE, dense, DENSE_COLUMNS, stamp, header.frame_id)


def message_cloud(
    msg: PointCloud2, columns: Sequence[str], mapping: dict[str, str], label: str
) -> PointCloud:
    """PointCloud2 -> cloud of the model ``columns`` (fields by name or ``mapping``), non-finite
    rows dropped and counted; MsdnetError (``label``: cause) for a message that cannot be read."""
    points = int(msg.width) * int(msg.height)
    if points > MAX_POINTS:
        raise MsdnetError(label, f"{points} points exceeds the cap of {MAX_POINTS} per scan")
    fields = resolve_fields(msg, columns, mapping, label)
    view = dataclasses.replace(msg, data=np.frombuffer(bytes(msg.data), dtype=np.uint8))
    try:
        values = pointcloud2_to_array(view, fields)  # (N, len(columns)) float32
    except ValueError as err:
        raise MsdnetError(label, str(err)) from None
    return cloud_from_array(label, values, tuple(columns))


def message_array(msg: PointCloud2) -> np.ndarray:
    """Every field of a float32 PointCloud2 (e.g. a ``/dense`` message) -> (N, C) float32."""
    view = dataclasses.replace(msg, data=np.frombuffer(bytes(msg.data), dtype=np.uint8))
    return pointcloud2_to_array(view, list(msg.fields))
