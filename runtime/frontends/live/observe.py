"""``msdnet-node``'s own timing and health, published as Autoware's nodes publish theirs.

- ``~/debug/processing_time_ms``: one scan's processing, from taking it to its output written
  (the node's ``service_ms``); ``~/debug/cyclic_time_ms``: time between the starts of two
  scans' processing; ``~/debug/pipeline_latency_ms``: now (wall clock) minus the input header
  stamp, at publish. Type ``Float64Stamped`` of ``autoware_internal_debug_msgs`` or
  ``tier4_debug_msgs`` (parameter ``debug_msgs_type``; the same fields, another DDS type name).
  ``~`` is the node's namespace and name: ``/msdnet_node/debug/...``.
- ``/diagnostics``: a ``diagnostic_msgs/DiagnosticArray`` with one status ``msdnet_node:
  processing_time``: OK; WARN when the last scan took longer than
  ``max_allowed_processing_time_ms``; ERROR when processing has stayed above that limit for longer
  than ``max_acceptable_consecutive_delay_ms`` (measured from the end of the last scan within the
  limit). Published after every scan and once a second while no scan comes.

All reliable, volatile, keep last 1.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from msdnet.runtime.frontends.live.idl import (
    DEBUG_TYPES,
    DiagnosticArray,
    DiagnosticStatus,
    Header,
    KeyValue,
    Time,
    dds_topic,
)

NODE_NAMESPACE = "/msdnet_node"  # ~ of the debug topics
DEBUG_TOPICS = ("processing_time_ms", "cyclic_time_ms", "pipeline_latency_ms")
DIAGNOSTICS_TOPIC = "/diagnostics"
STATUS_NAME = "msdnet_node: processing_time"
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}
DIAGNOSTICS_PERIOD_S = 1.0  # while no scan comes, as diagnostic_updater's default period


def wall_time() -> Time:
    """Now (system clock) as builtin_interfaces/Time."""
    sec, nsec = divmod(time.time_ns(), 10**9)
    return Time(int(sec), int(nsec))


def debug_topic(name: str) -> str:
    """``processing_time_ms`` -> ``/msdnet_node/debug/processing_time_ms``."""
    return f"{NODE_NAMESPACE}/debug/{name}"


@dataclass
class Health:
    """The diagnostics state: OK / WARN / ERROR from the processing times (module docstring)."""

    max_allowed_ms: float
    max_consecutive_ms: float
    level: int = OK
    message: str = "no scan yet"
    last_ms: float | None = None
    last_in_time: float | None = None  # monotonic end of the last scan within the limit
    delay_ms: float = 0.0  # how long processing has stayed above the limit

    def update(self, processing_ms: float, now: float) -> int:
        """Take one scan's processing time (ended at monotonic ``now``); -> the new level."""
        self.last_ms = processing_ms
        if processing_ms <= self.max_allowed_ms:
            self.last_in_time, self.delay_ms = now, 0.0
            self.level, self.message = OK, "processing time within the limit"
            return self.level
        if self.last_in_time is None:  # slow from the first scan: the streak starts with it
            self.last_in_time = now - processing_ms / 1e3
        self.delay_ms = (now - self.last_in_time) * 1e3
        if self.delay_ms > self.max_consecutive_ms:
            self.level = ERROR
            self.message = (
                f"processing time above {self.max_allowed_ms:g} ms for {self.delay_ms:.0f} ms "
                f"(> {self.max_consecutive_ms:g} ms)"
            )
        else:
            self.level = WARN
            self.message = f"processing time {processing_ms:.1f} ms above {self.max_allowed_ms:g} ms"
        return self.level

    def status(self, hardware_id: str) -> DiagnosticStatus:
        values = [
            KeyValue("processing_time_ms", "" if self.last_ms is None else f"{self.last_ms:.3f}"),
            KeyValue("max_allowed_processing_time_ms", f"{self.max_allowed_ms:g}"),
            KeyValue("consecutive_delay_ms", f"{self.delay_ms:.1f}"),
            KeyValue("max_acceptable_consecutive_delay_ms", f"{self.max_consecutive_ms:g}"),
        ]
        return DiagnosticStatus(self.level, STATUS_NAME, self.message, hardware_id, values)


class Observer:
    """The debug and diagnostics writers of one node (``dds``: its Endpoints)."""

    def __init__(self, dds: Any, cfg: Any, hardware_id: str) -> None:
        self.health = Health(cfg.max_allowed_processing_time_ms, cfg.max_acceptable_consecutive_delay_ms)
        self.hardware_id = hardware_id
        self.debug: dict[str, Any] = {}
        if cfg.publish_debug:
            struct = DEBUG_TYPES[cfg.debug_msgs_type]
            self._float = struct
            for name in DEBUG_TOPICS:
                self.debug[name] = dds.writer(dds_topic(debug_topic(name)), reliable=True, struct=struct)
        self.diagnostics = None
        if cfg.publish_diagnostics:
            self.diagnostics = dds.writer(dds_topic(DIAGNOSTICS_TOPIC), reliable=True, struct=DiagnosticArray)
        self._last_diag = 0.0

    def scan(self, processing_ms: float, cyclic_ms: float | None, latency_ms: float, now: float) -> int:
        """Publish one scan's debug values and the diagnostics; -> the diagnostics level."""
        if self.debug:
            stamp = wall_time()
            self.debug["processing_time_ms"].write(self._float(stamp, float(processing_ms)))
            if cyclic_ms is not None:
                self.debug["cyclic_time_ms"].write(self._float(stamp, float(cyclic_ms)))
            self.debug["pipeline_latency_ms"].write(self._float(stamp, float(latency_ms)))
        level = self.health.update(processing_ms, now)
        self.publish_diagnostics(now)
        return level

    def publish_diagnostics(self, now: float) -> None:
        """Write the diagnostics now (``now``: monotonic)."""
        if self.diagnostics is None:
            return
        header = Header(wall_time(), "")
        self.diagnostics.write(DiagnosticArray(header, [self.health.status(self.hardware_id)]))
        self._last_diag = now

    def idle(self, now: float) -> None:
        """Called while no scan comes: the diagnostics once a ``DIAGNOSTICS_PERIOD_S``."""
        if now - self._last_diag >= DIAGNOSTICS_PERIOD_S:
            self.publish_diagnostics(now)
