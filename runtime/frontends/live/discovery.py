"""Writers on the node's input topic that its reader cannot match, each named once on stderr.

DDS matches a reader and a writer only when the topic name, the type and the QoS agree, and
otherwise says nothing to either side: a PointCloud2 publisher on a topic where the node reads
RadarScan would get silence. Every participant announces its writers on the builtin
``DCPSPublication`` topic (topic name, type name, QoS); :class:`WriterWatch` reads it and, for a
writer on the input topic that the reader has not matched (``get_matched_publications``), says in
one line why:

- its type name differs (``sensor_msgs/msg/PointCloud2`` where ``radar_msgs/msg/RadarScan`` is
  read): said as soon as the writer is seen;
- its QoS cannot match (a best-effort writer where the reader is reliable, or a data
  representation without XCDR1): said as soon as seen;
- same type name and QoS, still unmatched after ``MATCH_GRACE_S``: its type definition differs
  from the published ``.msg`` (a cyclonedds peer compares the full type object).

Each cause is said once per type name (a publisher that restarts is not named again).
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from typing import Any

MATCH_GRACE_S = 3.0  # a writer of the same type and QoS unmatched this long after it was seen
_DDS_TYPE = re.compile(r"^(\w+)::(msg|srv|action)::dds_::(\w+)_$")


def ros_type(dds_type: str) -> str:
    """``sensor_msgs::msg::dds_::PointCloud2_`` -> ``sensor_msgs/msg/PointCloud2`` (else as is)."""
    m = _DDS_TYPE.match(dds_type)
    return f"{m.group(1)}/{m.group(2)}/{m.group(3)}" if m else dds_type


def _qos_mismatch(qos: Any, reliable: bool) -> str | None:
    """Why a writer with ``qos`` cannot match this node's reader (reliable or not), or None."""
    from cyclonedds.qos import Policy

    text = str(qos)
    if reliable and "Reliability.BestEffort" in text:
        return "it is best effort and this node's subscription is reliable (input_reliability: reliable)"
    for policy in qos:  # XCDR2 only: this node reads XCDR1 (plain CDR)
        if isinstance(policy, Policy.DataRepresentation) and not policy.use_cdrv0_representation:
            return "it writes XCDR2 only and this node reads plain CDR (XCDR1), as ROS 2 does"
    return None


class WriterWatch:
    """Polled by the receive thread: names each unmatched writer's cause once (``warn``)."""

    def __init__(
        self,
        participant: Any,
        reader: Any,
        dds_topic: str,
        ros_topic: str,
        dds_type: str,
        reliable: bool,
        warn: Callable[[str], None],
    ) -> None:
        from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication

        self.builtin = BuiltinDataReader(participant, BuiltinTopicDcpsPublication)
        self.reader, self.dds_topic, self.ros_topic = reader, dds_topic, ros_topic
        self.dds_type, self.reliable, self.warn = dds_type, reliable, warn
        self.seen: dict[int, tuple[Any, float]] = {}  # instance handle -> (sample, first seen)
        self.said: set[tuple[str, str]] = set()  # (type name, cause kind) already named
        self.count = 0  # writers named

    def poll(self) -> None:
        """Take new announcements; name the writers that cannot match (module docstring)."""
        now = time.monotonic()
        for s in self.builtin.take(N=64):
            handle = s.sample_info.instance_handle
            if not s.sample_info.valid_data:
                self.seen.pop(handle, None)
            elif s.topic_name == self.dds_topic:
                self.seen.setdefault(handle, (s, now))
        if not self.seen:
            return
        matched = set(self.reader.get_matched_publications())
        for handle, (s, since) in list(self.seen.items()):
            if handle in matched:
                del self.seen[handle]
                continue
            why = self._cause(s, now - since)
            if why is None:
                continue
            del self.seen[handle]
            kind, text = why
            if (s.type_name, kind) not in self.said:
                self.said.add((s.type_name, kind))
                self.count += 1
                self.warn(f"a writer on {self.ros_topic} is not matched: {text}; its messages are not read")

    def _cause(self, s: Any, waited: float) -> tuple[str, str] | None:
        if s.type_name != self.dds_type:
            return "type", (
                f"it publishes {ros_type(s.type_name)}, this node reads {ros_type(self.dds_type)} "
                "(input_type)"
            )
        qos = _qos_mismatch(s.qos, self.reliable)
        if qos is not None:
            return "qos", qos
        if waited >= MATCH_GRACE_S:
            return "definition", (
                f"its {ros_type(s.type_name)} is defined otherwise than the published .msg "
                "(field names or types differ)"
            )
        return None
