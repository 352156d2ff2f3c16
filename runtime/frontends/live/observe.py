"""``msdnet-node``'s own timing and health, published as Autoware's nodes publish theirs.

- ``~/debug/processing_time_ms``: one scan's processing, from taking it to its output written
  (the node's ``service_ms``); ``~/debug/cyclic_time_ms``: time between the starts of two
  scans' processing; ``~/debug/pipeline_latency_ms``: now (wall clock) minus the input header
  stamp, at publish. Type ``Float64Stamped`` of ``autoware_internal_debug_msgs`` or
  ``tier4_debug_msgs`` (parameter ``debug_msgs_type``; the same fields, another DDS type name).
  ``~`` is the node's namespace and name (``node_name``, ``namespace``): ``/msdnet_node/debug/...``
  by default.
- ``/diagnostics``: a ``diagnostic_msgs/DiagnosticArray`` with one status ``<node_name>:
  processing_time`` (as ``diagnostic_updater`` names a node's status) and hardware_id
  ``<namespace/node_name> <input_topic>``: OK; WARN when the last scan took longer than
  ``max_allowed_processing_time_ms``; ERROR when processing has stayed above that limit for longer
  than ``max_acceptable_consecutive_delay_ms`` (measured from the end of the last scan within the
  limit). Published every ``diagnostics_period_s`` (1 s by default, ``diagnostic_updater``'s
  period) from a thread of its own, carrying the latest state, whether scans come or not and
  however long one takes.

All reliable, volatile, keep last 1.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
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

DEBUG_TOPICS = ("processing_time_ms", "cyclic_time_ms", "pipeline_latency_ms")
DIAGNOSTICS_TOPIC = "/diagnostics"
TASK = "processing_time"  # the diagnostic task; its status is "<node name>: processing_time"
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}


def wall_time() -> Time:
    """Now (system clock) as builtin_interfaces/Time."""
    sec, nsec = divmod(time.time_ns(), 10**9)
    return Time(int(sec), int(nsec))


def debug_topic(name: str, fqn: str = "/msdnet_node") -> str:
    """``processing_time_ms`` of the node ``fqn`` -> ``/msdnet_node/debug/processing_time_ms``."""
    return f"{fqn.rstrip('/')}/debug/{name}"


def node_topics(cfg: Any) -> dict[str, str]:
    """Every topic the node ``cfg`` writes: {what: ROS topic} (the dense cloud, the debug topics
    and /diagnostics when published)."""
    out = {"output_topic": cfg.dense_topic}
    if cfg.publish_debug:
        out |= {f"~/debug/{name}": debug_topic(name, cfg.fqn) for name in DEBUG_TOPICS}
    if cfg.publish_diagnostics:
        out["/diagnostics"] = DIAGNOSTICS_TOPIC
    return out


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
    running_since: float | None = None  # monotonic start of the scan in hand (None: idle)
    lock: threading.Lock = field(default_factory=threading.Lock)  # update() against status()

    def begin(self, now: float | None) -> None:
        """A scan's processing starts (monotonic ``now``; None: no scan runs any more): a status
        taken while it runs counts it."""
        with self.lock:
            self.running_since = now

    def update(self, processing_ms: float, now: float) -> int:
        """Take one scan's processing time (ended at monotonic ``now``); -> the new level."""
        with self.lock:
            self.running_since = None
            return self._update(processing_ms, now)

    def _update(self, processing_ms: float, now: float) -> int:
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

    def status(self, name: str, hardware_id: str, now: float) -> DiagnosticStatus:
        """The latest state at monotonic ``now`` as the status ``name`` of ``hardware_id``: the last
        scan's, or the running scan's once it has run past the limit (a stuck scan is not OK)."""
        with self.lock:
            level, message, delay = self.level, self.message, self.delay_ms
            running_ms = None if self.running_since is None else (now - self.running_since) * 1e3
            if running_ms is not None and running_ms > self.max_allowed_ms:
                start = self.running_since if self.last_in_time is None else self.last_in_time
                delay = max(delay, (now - start) * 1e3)
                level = ERROR if delay > self.max_consecutive_ms else max(level, WARN)
                message = f"a scan has run {running_ms:.0f} ms, above {self.max_allowed_ms:g} ms"
            values = [
                KeyValue("processing_time_ms", "" if self.last_ms is None else f"{self.last_ms:.3f}"),
                KeyValue("max_allowed_processing_time_ms", f"{self.max_allowed_ms:g}"),
                KeyValue("consecutive_delay_ms", f"{delay:.1f}"),
                KeyValue("max_acceptable_consecutive_delay_ms", f"{self.max_consecutive_ms:g}"),
            ]
        return DiagnosticStatus(level, name, message, hardware_id, values)


class Observer:
    """The debug and diagnostics writers of one node (``dds``: its Endpoints); :meth:`start`
    publishes the diagnostics every ``cfg.diagnostics_period_s`` until :meth:`close`."""

    def __init__(self, dds: Any, cfg: Any) -> None:
        self.health = Health(cfg.max_allowed_processing_time_ms, cfg.max_acceptable_consecutive_delay_ms)
        self.status_name = f"{cfg.node_name}: {TASK}"
        self.hardware_id = f"{cfg.fqn.lstrip('/')} {cfg.topic}"
        self.period_s = cfg.diagnostics_period_s
        self.debug: dict[str, Any] = {}
        if cfg.publish_debug:
            struct = DEBUG_TYPES[cfg.debug_msgs_type]
            self._float = struct
            for name in DEBUG_TOPICS:
                topic = dds_topic(debug_topic(name, cfg.fqn))
                self.debug[name] = dds.writer(topic, reliable=True, struct=struct)
        self.diagnostics = None
        if cfg.publish_diagnostics:
            self.diagnostics = dds.writer(dds_topic(DIAGNOSTICS_TOPIC), reliable=True, struct=DiagnosticArray)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.published = 0  # DiagnosticArray messages written

    def scan(self, processing_ms: float, cyclic_ms: float | None, latency_ms: float, now: float) -> int:
        """Publish one scan's debug values and take its time into the diagnostics state; -> the
        diagnostics level (published by the period, not here)."""
        if self.debug:
            stamp = wall_time()
            self.debug["processing_time_ms"].write(self._float(stamp, float(processing_ms)))
            if cyclic_ms is not None:
                self.debug["cyclic_time_ms"].write(self._float(stamp, float(cyclic_ms)))
            self.debug["pipeline_latency_ms"].write(self._float(stamp, float(latency_ms)))
        return self.health.update(processing_ms, now)

    def publish_diagnostics(self) -> None:
        """Write the latest diagnostics state now."""
        if self.diagnostics is None:
            return
        header = Header(wall_time(), "")
        status = self.health.status(self.status_name, self.hardware_id, time.monotonic())
        self.diagnostics.write(DiagnosticArray(header, [status]))
        self.published += 1

    def start(self) -> None:
        """Publish the diagnostics now and then every period, on a fixed schedule, in a thread."""
        if self.diagnostics is None:
            return

        def run() -> None:
            next_at = time.monotonic()
            while True:
                self.publish_diagnostics()
                next_at = max(next_at + self.period_s, time.monotonic())  # no burst after a stall
                if self._stop.wait(next_at - time.monotonic()):
                    return

        self._thread = threading.Thread(target=run, name="msdnet-node-diagnostics", daemon=True)
        self._thread.start()

    def close(self, timeout: float = 1.0) -> bool:
        """Stop the periodic thread; -> True when it has ended (the writers may be deleted)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True
