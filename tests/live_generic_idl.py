"""PointCloud2 with cyclonedds' generic sequence<octet> machine (for tests/test_live_node.py).

No ``from __future__ import annotations``: the IDL machinery resolves the annotations itself.
"""

from dataclasses import dataclass

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import sequence, uint8, uint32

from msdnet.runtime.frontends.live.idl import Header, PointField


@dataclass
class GenericPointCloud2(IdlStruct, typename="sensor_msgs::msg::dds_::PointCloud2_"):
    """sensor_msgs/msg/PointCloud2 as the binding serializes it without runtime/frontends/live/idl's patch."""

    header: Header
    height: uint32
    width: uint32
    fields: sequence[PointField]
    is_bigendian: bool
    point_step: uint32
    row_step: uint32
    data: sequence[uint8]
    is_dense: bool
