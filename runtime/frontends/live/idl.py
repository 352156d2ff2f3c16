"""ROS 2 message types as Cyclone DDS IDL structs, written once (torch-free, no ROS install).

ROS 2 (every rmw over DDS) names the DDS type of ``pkg/msg/Name`` ``pkg::msg::dds_::Name_`` and
the DDS topic of the ROS topic ``/a/b`` ``rt/a/b``. The structs below follow the ROS 2 ``.msg``
definitions field for field, so their CDR bytes are those of a ROS 2 node's messages. (No
``from __future__ import annotations`` here: the IDL machinery resolves the annotations itself.)
"""

import re
from dataclasses import dataclass
from typing import Any

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import byte, float32, float64, int32, sequence, uint8, uint32

from msdnet.runtime.errors import MsdnetError

ROS_TOPIC_PREFIX = "rt"  # ROS 2 topics are DDS topics "rt" + the ROS name
_ROS_NAME = re.compile(r"^/?[A-Za-z_~][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    """builtin_interfaces/msg/Time."""

    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    """std_msgs/msg/Header (ROS 2: no seq)."""

    stamp: Time
    frame_id: str


@dataclass
class PointField(IdlStruct, typename="sensor_msgs::msg::dds_::PointField_"):
    """sensor_msgs/msg/PointField: datatype 1..8 = INT8 UINT8 INT16 UINT16 INT32 UINT32 FLOAT32 FLOAT64."""

    name: str
    offset: uint32
    datatype: uint8
    count: uint32


@dataclass
class PointCloud2(IdlStruct, typename="sensor_msgs::msg::dds_::PointCloud2_"):
    """sensor_msgs/msg/PointCloud2; ``data`` is height * row_step bytes."""

    header: Header
    height: uint32
    width: uint32
    fields: sequence[PointField]
    is_bigendian: bool
    point_step: uint32
    row_step: uint32
    data: sequence[uint8]
    is_dense: bool


@dataclass
class RadarReturn(IdlStruct, typename="radar_msgs::msg::dds_::RadarReturn_"):
    """radar_msgs/msg/RadarReturn: one return in polar form (metres, radians, m/s, dB); azimuth
    positive anticlockwise (REP 103), elevation positive up."""

    range: float32
    azimuth: float32
    elevation: float32
    doppler_velocity: float32
    amplitude: float32


@dataclass
class RadarScan(IdlStruct, typename="radar_msgs::msg::dds_::RadarScan_"):
    """radar_msgs/msg/RadarScan (the array is ``returns``, as published since mid-2020)."""

    header: Header
    returns: sequence[RadarReturn]


@dataclass
class Tier4Float64Stamped(IdlStruct, typename="tier4_debug_msgs::msg::dds_::Float64Stamped_"):
    """tier4_debug_msgs/msg/Float64Stamped (deprecated by Autoware, still watched by older stacks)."""

    stamp: Time
    data: float64


@dataclass
class AutowareFloat64Stamped(IdlStruct, typename="autoware_internal_debug_msgs::msg::dds_::Float64Stamped_"):
    """autoware_internal_debug_msgs/msg/Float64Stamped (same fields as the tier4 type)."""

    stamp: Time
    data: float64


DEBUG_TYPES = {  # the debug_msgs_type parameter -> the struct of its Float64Stamped
    "tier4_debug_msgs": Tier4Float64Stamped,
    "autoware_internal_debug_msgs": AutowareFloat64Stamped,
}


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    """diagnostic_msgs/msg/KeyValue."""

    key: str
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    """diagnostic_msgs/msg/DiagnosticStatus; ``level`` is ``byte`` (IDL octet): OK 0, WARN 1,
    ERROR 2, STALE 3."""

    level: byte
    name: str
    message: str
    hardware_id: str
    values: sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    """diagnostic_msgs/msg/DiagnosticArray."""

    header: Header
    status: sequence[DiagnosticStatus]


def dds_topic(ros_name: str) -> str:
    """ROS 2 topic name -> DDS topic name (``/radar/points`` -> ``rt/radar/points``);
    MsdnetError naming ``--topic`` for a name ROS 2 would refuse."""
    if not _ROS_NAME.match(ros_name) or ros_name.startswith("/~"):
        raise MsdnetError("--topic", f"{ros_name!r} is not a ROS 2 topic name (e.g. /radar/points)")
    return f"{ROS_TOPIC_PREFIX}/{ros_name.lstrip('/')}"


def _data_as_bytes(struct: type) -> None:
    """Serialize ``struct.data`` (``sequence[uint8]``) from / to ``bytes`` in one copy instead of
    element by element (~25 ms for a 800 kB cloud). The wire format is unchanged: a uint32
    length, then the bytes (XCDR1 and XCDR2 alike); the type object still says
    ``sequence<octet>``, so ROS 2 readers and writers match it. tests/test_live_node.py checks
    the bytes against the generic machine."""
    from cyclonedds.idl._machinery import BytesMachine

    struct.__idl__.populate()
    for name in ("v1_machine", "v2_machine"):
        machine = getattr(struct.__idl__, name, None)
        if machine is not None and "data" in getattr(machine, "members_machines", {}):
            machine.members_machines["data"] = BytesMachine()


_data_as_bytes(PointCloud2)


def _returns_as_array(struct: type) -> None:
    """Serialize ``RadarScan.returns`` from / to a (N, 5) float32 array [range, azimuth,
    elevation, doppler_velocity, amplitude] in one copy instead of one struct per return. The
    wire format is unchanged: a uint32 count, then five 4-byte floats per return (a RadarReturn
    is five float32, so no padding; XCDR1 and XCDR2 alike); the type object still says
    ``sequence<radar_msgs::msg::RadarReturn>``. Serializing also takes a list of RadarReturn."""
    import numpy as np
    from cyclonedds.idl._machinery import BytesMachine

    class ReturnsMachine(BytesMachine):
        def serialize(self, buffer: Any, value: Any, *args: Any, **kwargs: Any) -> None:
            if not isinstance(value, np.ndarray):
                value = [[r.range, r.azimuth, r.elevation, r.doppler_velocity, r.amplitude] for r in value]
            arr = np.asarray(value, dtype=buffer._endian + "f4").reshape(-1, 5)
            buffer.align(4)
            buffer.write("I", 4, arr.shape[0])
            buffer.write_bytes(arr.tobytes())

        def deserialize(self, buffer: Any, *args: Any, **kwargs: Any) -> Any:
            buffer.align(4)
            count = buffer.read("I", 4)
            raw = buffer.read_bytes(20 * count)
            return np.frombuffer(raw, dtype=buffer._endian + "f4").reshape(count, 5).astype(np.float32)

        def default_initialize(self) -> Any:
            return np.empty((0, 5), np.float32)

    struct.__idl__.populate()
    for name in ("v1_machine", "v2_machine"):
        machine = getattr(struct.__idl__, name, None)
        if machine is not None and "returns" in getattr(machine, "members_machines", {}):
            machine.members_machines["returns"] = ReturnsMachine()


_returns_as_array(RadarScan)
