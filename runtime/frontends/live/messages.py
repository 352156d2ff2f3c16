"""Radar messages (PointCloud2, RadarScan) -> model clouds, and clouds -> output PointCloud2.

``io.rosbag`` reads a PointCloud2 by field name (``--field`` overrides) and writes float32 clouds;
the same functions serve the live node: :data:`IDL_STORE` makes ``io.rosbag.make_pointcloud2``
build the IDL structs of :mod:`msdnet.runtime.frontends.live.idl`, and :func:`message_cloud`
feeds them to ``io.rosbag.pointcloud2_to_array``.

Inputs:

- **PointCloud2**: each model column comes from a field: ``--field COLUMN=FIELD`` first, then the
  field preset (:data:`PRESETS`: the layouts of VoD, Astyx, the Continental ARS548 of
  tier4/nebula and the TI mmWave driver), then the field of the column's own (canonical) name.
  A message must agree with its own header: ``data`` holds exactly ``height * row_step`` bytes
  (:func:`check_claims`, the shared check of ``io.rosbag``); one that holds more or fewer is
  refused in one line, never cut.
- **RadarScan**: each return (range, azimuth, elevation, doppler_velocity, amplitude) becomes
  x = r cos(el) cos(az), y = r cos(el) sin(az), z = r sin(el) (REP 103: azimuth anticlockwise,
  elevation up; computed in float64, stored float32) with ``v_r`` = doppler_velocity and
  ``amplitude``: :data:`RADAR_SCAN_COLUMNS`. Model columns take them by the ``radar_scan`` preset
  (rcs / mag / intensity <- amplitude, v_r and v_r_compensated <- v_r) unless ``--field`` says
  otherwise.

Output (:func:`output_message`): float32 ``x y z confidence`` (point_step 16, little-endian,
height 1) plus, with ``--keep-radar``, the input's own fields feeding the model (e.g. ``rcs``,
``v_r``): set on the kept radar rows, NaN on the model's rows.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np

from msdnet.runtime.engine.pointcloud import XYZ, PointCloud, canonical_column
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.live.idl import Header, PointCloud2, PointField, RadarScan, Time
from msdnet.runtime.io.files import DENSE_COLUMNS, MAX_POINTS, cloud_from_array
from msdnet.runtime.io.rosbag import (
    POINTCLOUD2,
    check_pointcloud2_size,
    make_pointcloud2,
    pointcloud2_to_array,
    resolve_fields,
)

RADAR_SCAN_COLUMNS = ("x", "y", "z", "v_r", "amplitude")  # a RadarScan's returns as a cloud
AMPLITUDE_COLUMNS = ("rcs", "mag", "magnitude", "intensity", "amplitude", "snr")  # one quantity
# preset -> {quantity: field names tried in turn, exactly, then by canonical name}
PRESETS: dict[str, dict[str, tuple[str, ...]]] = {
    "vod": {"amplitude": ("RCS", "rcs"), "v_r": ("v_r",), "v_r_compensated": ("v_r_compensated",)},
    "astyx": {"amplitude": ("Magnitude", "mag"), "v_r": ("v_r",), "v_r_compensated": ("v_r",)},
    "ars548": {"amplitude": ("rcs",), "v_r": ("range_rate",), "v_r_compensated": ("range_rate",)},
    "ti": {"amplitude": ("intensity",), "v_r": ("velocity",), "v_r_compensated": ("velocity",)},
    "radar_scan": {"amplitude": ("amplitude",), "v_r": ("v_r",), "v_r_compensated": ("v_r",)},
}
UNCOMPENSATED = ("astyx", "ars548", "ti", "radar_scan")  # presets with no ego-motion compensation


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


def stamp_of(msg: Any) -> tuple[int, int]:
    """(sec, nanosec) of the message's header."""
    return int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)


def quantity(column: str) -> str:
    """The quantity a model column holds, as presets name it (``mag`` -> ``amplitude``)."""
    return "amplitude" if column in AMPLITUDE_COLUMNS else column


def preset_note(preset: str, columns: Sequence[str]) -> str | None:
    """One line when ``preset`` feeds the model's ``v_r_compensated`` with an uncompensated
    radial velocity (the sensor reports no ego-motion compensated one); else None."""
    if preset in UNCOMPENSATED and "v_r_compensated" in columns:
        field = PRESETS[preset]["v_r_compensated"][0]
        return (
            f"note: the model's column v_r_compensated is fed the uncompensated radial velocity "
            f"{field!r} ({preset} layout has no ego-motion compensated velocity)"
        )
    return None


def field_mapping(
    names: Sequence[str], columns: Sequence[str], mapping: dict[str, str], preset: str | None
) -> dict[str, str]:
    """{model column: message field} for a message with fields ``names``: ``mapping`` (``--field``)
    first, then ``preset``'s field for the column's quantity; other columns match by name later."""
    out = dict(mapping)
    if not preset:
        return out
    canon = {canonical_column(n): n for n in names}
    for col in columns:
        if col in out or col in XYZ:
            continue
        for candidate in PRESETS[preset].get(quantity(col), ()):
            found = candidate if candidate in names else canon.get(canonical_column(candidate))
            if found is not None:
                out[col] = found
                break
    return out


def check_claims(msg: Any, label: str) -> None:
    """A PointCloud2 must agree with its own header (``io.rosbag.check_pointcloud2_size``: ``data``
    holds exactly ``height`` rows of ``row_step`` bytes) and stay under the point cap;
    MsdnetError naming ``label`` otherwise: a message holding more points than it claims is
    refused, never cut."""
    claimed = int(msg.width) * int(msg.height)
    if claimed > MAX_POINTS:
        raise MsdnetError(label, f"{claimed} points exceeds the cap of {MAX_POINTS} per scan")
    try:
        check_pointcloud2_size(msg)
    except ValueError as err:
        raise MsdnetError(label, str(err)) from None


def message_cloud(
    msg: PointCloud2,
    columns: Sequence[str],
    mapping: dict[str, str],
    label: str,
    preset: str | None = None,
) -> tuple[PointCloud, tuple[str, ...]]:
    """PointCloud2 -> (cloud of the model ``columns``, the message field feeding each column);
    non-finite rows dropped and counted; MsdnetError (``label``: cause) for a message that cannot
    be read or whose data disagrees with its header."""
    check_claims(msg, label)
    names = [f.name for f in msg.fields]
    fields = resolve_fields(msg, columns, field_mapping(names, columns, mapping, preset), label)
    view = dataclasses.replace(msg, data=np.frombuffer(bytes(msg.data), dtype=np.uint8))
    try:
        values = pointcloud2_to_array(view, fields, label)  # (N, len(columns)) float32
    except ValueError as err:
        raise MsdnetError(label, str(err)) from None
    return cloud_from_array(label, values, tuple(columns)), tuple(f.name for f in fields)


def polar_to_points(returns: np.ndarray) -> np.ndarray:
    """(N, 5) [range, azimuth, elevation, doppler_velocity, amplitude] -> (N, 5) float32
    [x, y, z, v_r, amplitude] (REP 103 angles; the trigonometry in float64)."""
    ret = np.asarray(returns, dtype=np.float64).reshape(-1, 5)
    r, az, el = ret[:, 0], ret[:, 1], ret[:, 2]
    out = np.empty((ret.shape[0], 5), np.float64)
    out[:, 0] = r * np.cos(el) * np.cos(az)
    out[:, 1] = r * np.cos(el) * np.sin(az)
    out[:, 2] = r * np.sin(el)
    out[:, 3:] = ret[:, 3:]
    with np.errstate(over="ignore", invalid="ignore"):
        return out.astype(np.float32)


def points_to_polar(points: np.ndarray) -> np.ndarray:
    """(N, >= 3) [x, y, z, ...] -> (N, 5) float32 returns [range, azimuth, elevation, v_r, amp]
    (the last two from columns 3 and 4 when present, else 0): a test and benchmark helper."""
    p = np.asarray(points, dtype=np.float64)
    r = np.linalg.norm(p[:, :3], axis=1)
    out = np.zeros((p.shape[0], 5), np.float64)
    out[:, 0] = r
    out[:, 1] = np.arctan2(p[:, 1], p[:, 0])
    out[:, 2] = np.arcsin(np.divide(p[:, 2], r, out=np.zeros_like(r), where=r > 0))
    extra = min(p.shape[1] - 3, 2)
    out[:, 3 : 3 + extra] = p[:, 3 : 3 + extra]
    return out.astype(np.float32)


def radar_scan_cloud(
    msg: RadarScan, columns: Sequence[str], mapping: dict[str, str], label: str
) -> tuple[PointCloud, tuple[str, ...]]:
    """RadarScan -> (cloud of the model ``columns``, the field of :data:`RADAR_SCAN_COLUMNS`
    feeding each column), by ``mapping`` (``--field``) then the ``radar_scan`` preset."""
    returns = np.asarray(msg.returns, dtype=np.float32).reshape(-1, 5)
    if returns.shape[0] > MAX_POINTS:
        raise MsdnetError(label, f"{returns.shape[0]} returns exceeds the cap of {MAX_POINTS} per scan")
    table = polar_to_points(returns)
    picked = field_mapping(RADAR_SCAN_COLUMNS, columns, mapping, "radar_scan")
    names: list[str] = []
    for col in columns:
        name = picked.get(col, col)
        if name not in RADAR_SCAN_COLUMNS:
            raise MsdnetError(
                label,
                f"RadarScan has no field {name!r} for model column {col!r} (fields: "
                f"{' '.join(RADAR_SCAN_COLUMNS)}); map one with --field {col}=FIELD",
            )
        names.append(name)
    values = table[:, [RADAR_SCAN_COLUMNS.index(n) for n in names]]
    return cloud_from_array(label, values, tuple(columns)), tuple(names)


def radar_scan_message(returns: np.ndarray, stamp: tuple[int, int], frame_id: str) -> RadarScan:
    """(N, 5) returns -> RadarScan with that stamp and frame."""
    arr = np.ascontiguousarray(returns, dtype=np.float32).reshape(-1, 5)
    return RadarScan(Header(Time(*stamp), frame_id), arr)


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


def output_table(
    points: np.ndarray,
    confidence: np.ndarray,
    kept: np.ndarray | None,
    transform: np.ndarray | None,
) -> np.ndarray:
    """(M, 4) [x y z confidence], or with ``kept`` (K, E) input values of the last K rows (the
    kept radar points) (M, 4 + E) with NaN on the model's rows; ``transform`` (4, 4) moves x y z."""
    xyz = np.asarray(points, dtype=np.float64)
    if transform is not None and xyz.shape[0]:
        xyz = xyz @ transform[:3, :3].T + transform[:3, 3]
    table = np.concatenate([xyz.astype(np.float32), confidence[:, None].astype(np.float32)], axis=1)
    if kept is None:
        return table
    extra = np.full((table.shape[0], kept.shape[1]), np.nan, np.float32)
    if kept.shape[0]:
        extra[-kept.shape[0] :] = kept
    return np.concatenate([table, extra], axis=1)


def output_names(extra: Sequence[str]) -> tuple[str, ...]:
    """``x y z confidence`` and the kept radar fields, a field already named so suffixed ``_in``."""
    names = list(DENSE_COLUMNS)
    for name in extra:
        names.append(name if name not in names else f"{name}_in")
    return tuple(names)


def output_message(table: np.ndarray, names: Sequence[str], header: Header, frame_id: str) -> PointCloud2:
    """The output PointCloud2: ``table`` (M, len(names)) float32, the input's stamp, ``frame_id``."""
    stamp = (int(header.stamp.sec), int(header.stamp.nanosec))
    return make_pointcloud2(IDL_STORE, table, names, stamp, frame_id)


def message_array(msg: PointCloud2) -> np.ndarray:
    """Every field of a float32 PointCloud2 (e.g. a ``/dense`` message) -> (N, C) float32."""
    view = dataclasses.replace(msg, data=np.frombuffer(bytes(msg.data), dtype=np.uint8))
    return pointcloud2_to_array(view, list(msg.fields))
