"""``msdnet-node``'s counters and latency windows, and the one-place slot between its threads.

:class:`NodeStats` is what the stats line and ``--stats-json`` print (``docs/live.md``, "The
stats"); :class:`LatestSlot` holds the one scan waiting while another is densified.
"""

from __future__ import annotations

import json
import threading
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.engine.pointcloud import DROP_REASONS
from msdnet.runtime.io.atomic import atomic_output

LATENCY_WINDOW = 100_000  # latencies kept for the percentiles (bounded memory)
SCAN_WINDOW = 1000  # scans whose own input point counts the stats JSON keeps


class LatestSlot:
    """One waiting item; a newer :meth:`put` replaces it. Thread-safe."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None

    def put(self, item: Any) -> bool:
        """Store ``item``; -> True when it replaced one nobody had taken (a drop)."""
        with self._cond:
            replaced = self._item is not None
            self._item = item
            self._cond.notify()
        return replaced

    def take(self, timeout: float) -> Any:
        """The waiting item (removing it), or None after ``timeout`` seconds."""
        with self._cond:
            if self._item is None:
                self._cond.wait(timeout)
            item, self._item = self._item, None
        return item


def _percentiles(values: deque) -> dict[str, float | None]:
    a = np.asarray(values, dtype=np.float64)
    if not a.size:
        return {"p50": None, "p90": None, "p99": None, "max": None, "count": 0}
    pct = {f"p{q}": float(np.percentile(a, q)) for q in (50, 90, 99)}
    return {**pct, "max": float(a.max()), "count": int(a.size)}


@dataclass
class NodeStats:
    """Counters and the latency windows (seconds; the debug values in ms); ``lock`` guards them."""

    received: int = 0  # valid samples taken from DDS
    published: int = 0  # dense clouds written
    dropped: int = 0  # scans replaced while waiting (latest-message-wins)
    bad: int = 0  # messages that could not be read or run
    latencies: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    service: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))  # take -> publish
    cyclic_ms: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    pipeline_latency_ms: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    points_in: int = 0  # input points of the published scans
    points_dropped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(DROP_REASONS, 0))
    scans: deque = field(default_factory=lambda: deque(maxlen=SCAN_WINDOW))  # per scan: see add_scan
    diagnostics: dict[str, int] = field(default_factory=lambda: {"OK": 0, "WARN": 0, "ERROR": 0})
    unmatched_writers: int = 0  # writers on the input topic the reader could not match (named on stderr)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add_scan(self, stamp: str, res_stats: dict[str, int]) -> None:
        """Count one published scan's input points and the ones the engine dropped, by reason."""
        drops = {k: int(res_stats.get(k, 0)) for k in DROP_REASONS}
        # points_in: the rows the pipeline was given; a reader's NaN/Inf rows came before it
        n_in = int(res_stats.get("points_in", 0)) + int(res_stats.get("dropped_nonfinite", 0))
        with self.lock:
            self.points_in += n_in
            for key, n in drops.items():
                self.points_dropped[key] += n
            self.scans.append({"stamp": stamp, "points_in": n_in, **drops})

    def summary(self) -> dict[str, Any]:
        """Counters, latency percentiles in milliseconds (None before the first message), the
        input points dropped (totals by reason, and per scan for the last ``SCAN_WINDOW``)."""
        with self.lock:
            lat = np.asarray(self.latencies, dtype=np.float64) * 1e3
            srv = np.asarray(self.service, dtype=np.float64) * 1e3
            body: dict[str, Any] = {
                "received": self.received,
                "published": self.published,
                "dropped": self.dropped,
                "bad": self.bad,
                "unmatched_writers": self.unmatched_writers,
            }
            points = {"in": self.points_in, **self.points_dropped}
            points["dropped"] = sum(self.points_dropped.values())
            scans = list(self.scans)
            cyclic, pipeline = deque(self.cyclic_ms), deque(self.pipeline_latency_ms)
            diagnostics = dict(self.diagnostics)
        pct = {f"p{q}": float(np.percentile(lat, q)) if lat.size else None for q in (50, 90, 99)}
        body["latency_ms"] = {**pct, "max": float(lat.max()) if lat.size else None, "count": int(lat.size)}
        body["service_ms"] = {  # one scan's own time (read, densify, publish), without the wait
            "p50": float(np.percentile(srv, 50)) if srv.size else None,
            "max": float(srv.max()) if srv.size else None,
        }
        body["processing_time_ms"] = _percentiles(deque(srv))  # = ~/debug/processing_time_ms
        body["cyclic_time_ms"] = _percentiles(cyclic)
        body["pipeline_latency_ms"] = _percentiles(pipeline)
        body["input_points"] = points
        body["input_points_per_scan"] = scans
        body["diagnostics"] = diagnostics
        return body

    def line(self) -> str:
        """``received 300, published 290, dropped 10, bad 0; latency ms p50 .. p90 .. p99 ..
        max ..; input points 61234, dropped 812 (NaN/Inf 0, outside the grid 812, ...)``"""
        s = self.summary()
        lat = s["latency_ms"]
        text = ", ".join(f"{k} {s[k]}" for k in ("received", "published", "dropped", "bad"))
        if lat["count"]:
            text += "; receive->publish ms " + " ".join(
                f"{k} {lat[k]:.1f}" for k in ("p50", "p90", "p99", "max")
            )
        pts = s["input_points"]
        why = ", ".join(f"{DROP_REASONS[k]} {pts[k]}" for k in DROP_REASONS)
        text += f"; input points {pts['in']}, dropped {pts['dropped']} ({why})"
        return f"msdnet-node: {text}"


def write_stats(
    path: Path, stats: NodeStats, engines: dict[str, Any] | None = None, stopped_while: str | None = None
) -> None:
    """The final stats as JSON at ``path`` (atomically); ``engines``: what ``engines_used`` says;
    ``stopped_while``: the node's state when it was stopped (``serving``, ``loading the model``, ...)."""
    body = stats.summary() | ({} if engines is None else {"engines": engines})
    body |= {} if stopped_while is None else {"stopped_while": stopped_while}
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(body, indent=1) + "\n", encoding="utf-8")


def engines_used(pipe: Any, provider: str) -> dict[str, Any]:
    """The provider asked for, the engine each graph runs on and the head graph, as JSON:
    ``{"provider": str, "graphs": {file: engine}, "head": "dense" | "coarse-to-fine" | None}``;
    ``pipe`` None (stopped while loading): no graph yet."""
    auto = getattr(pipe, "auto", None)
    if auto is None:  # a provider by name, or no pipeline yet: every graph on it
        return {"provider": provider, "graphs": {}, "head": None}
    graphs = {f: pick.engine for f, pick in auto.picks.items()}
    return {"provider": provider, "graphs": graphs, "head": None if auto.head is None else auto.head.head}
