"""``msdnet-node``'s loop: one Pipeline serving the latest radar scan of a DDS topic.

Threads: a receive thread takes every sample as it arrives (stamping the receive time) and puts
it in a one-place :class:`LatestSlot`; the main thread takes the waiting scan, densifies it and
publishes ``<topic>/dense``. A scan that arrives while one is being densified replaces the one
waiting (the replaced one is counted as dropped), so nothing queues without bound and the output
is never older than one scan's time plus one. Latency is receive -> publish, kept for the last
``LATENCY_WINDOW`` messages and printed as p50 / p90 / p99 / max. A message that cannot be read
or run is counted, named in one line on stderr, and the node goes on.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.densify import DensifyOptions, densify
from msdnet.runtime.io.atomic import atomic_output

LATENCY_WINDOW = 100_000  # latencies kept for the percentiles (bounded memory)
POLL_S = 0.05  # how often both threads look at the stop flag (SIGTERM -> exit well within 1 s)
DENSE_SUFFIX = "/dense"  # output topic = input topic + this


@dataclass(frozen=True)
class NodeConfig:
    """What one ``msdnet-node`` serves, and how."""

    topic: str  # ROS 2 topic of the radar PointCloud2, e.g. /radar/points (DDS rt/radar/points)
    domain_id: int = 0  # DDS domain id: the ROS_DOMAIN_ID of the ROS 2 system
    fields: tuple[str, ...] = ()  # --field model_column=msg_field overrides (as the bag mode)
    options: DensifyOptions = DensifyOptions()  # steps, threshold, seed, keep_radar: as file mode
    stats_every: int = 0  # print a stats line every N handled messages; 0: only at exit
    stats_json: Path | None = None  # also write the final stats here as JSON (atomic), if set


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


@dataclass
class NodeStats:
    """Counters and the latency window (seconds); ``lock`` guards the counters."""

    received: int = 0  # valid samples taken from DDS
    published: int = 0  # dense clouds written
    dropped: int = 0  # scans replaced while waiting (latest-message-wins)
    bad: int = 0  # messages that could not be read or run
    latencies: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    service: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))  # take -> publish
    lock: threading.Lock = field(default_factory=threading.Lock)

    def summary(self) -> dict[str, Any]:
        """Counters and latency percentiles in milliseconds (None before the first message)."""
        with self.lock:
            lat = np.asarray(self.latencies, dtype=np.float64) * 1e3
            srv = np.asarray(self.service, dtype=np.float64) * 1e3
            body: dict[str, Any] = {
                "received": self.received,
                "published": self.published,
                "dropped": self.dropped,
                "bad": self.bad,
            }
        pct = {f"p{q}": float(np.percentile(lat, q)) if lat.size else None for q in (50, 90, 99)}
        body["latency_ms"] = {**pct, "max": float(lat.max()) if lat.size else None, "count": int(lat.size)}
        body["service_ms"] = {  # one scan's own time (read, densify, publish), without the wait
            "p50": float(np.percentile(srv, 50)) if srv.size else None,
            "max": float(srv.max()) if srv.size else None,
        }
        return body

    def line(self) -> str:
        """``received 300, published 290, dropped 10, bad 0; latency ms p50 .. p90 .. p99 .. max ..``"""
        s = self.summary()
        lat = s["latency_ms"]
        text = ", ".join(f"{k} {s[k]}" for k in ("received", "published", "dropped", "bad"))
        if lat["count"]:
            text += "; receive->publish ms " + " ".join(
                f"{k} {lat[k]:.1f}" for k in ("p50", "p90", "p99", "max")
            )
        return f"msdnet-node: {text}"


def _receive(
    reader: Any,
    waitset: Any,
    slot: LatestSlot,
    stats: NodeStats,
    stop: threading.Event,
    bad: Callable[[str], None],
) -> None:
    """Receive thread: take samples one by one into ``slot`` until ``stop``."""
    from cyclonedds.util import duration

    index = 0
    while not stop.is_set():
        waitset.wait(duration(seconds=POLL_S))
        while not stop.is_set():
            try:
                samples = reader.take(N=1)
            except Exception as err:  # a sample whose bytes do not decode as a PointCloud2
                with stats.lock:
                    stats.bad += 1
                bad(f"message {index}: cannot decode as a PointCloud2: {' '.join(str(err).split())[:160]}")
                index += 1
                continue
            if not samples:
                break
            sample = samples[0]
            if not sample.sample_info.valid_data:  # a writer went away (dispose/unregister)
                continue
            with stats.lock:
                stats.received += 1
            if slot.put((sample, time.perf_counter(), index)):
                with stats.lock:
                    stats.dropped += 1
            index += 1


def serve(
    pipe: Any,
    cfg: NodeConfig,
    stop: threading.Event,
    echo: Callable[[str], None],
    warn: Callable[[str], None],
) -> NodeStats:
    """Serve ``cfg.topic`` with ``pipe`` until ``stop`` is set; -> the final stats. Prints a ready
    line once subscribed, a stats line every ``cfg.stats_every`` messages and one at the end."""
    from msdnet.runtime.frontends.live.dds import Endpoints
    from msdnet.runtime.frontends.live.idl import dds_topic
    from msdnet.runtime.frontends.live.messages import dense_message, message_cloud, stamp_of
    from msdnet.runtime.io.rosbag import parse_field_map

    in_topic = dds_topic(cfg.topic)
    out_name = cfg.topic.rstrip("/") + DENSE_SUFFIX
    mapping = parse_field_map(cfg.fields, pipe.columns)
    pipe.warmup()
    dds = Endpoints(cfg.domain_id)
    reader, writer = dds.reader(in_topic), dds.writer(dds_topic(out_name))
    waitset, _cond = dds.waitset(reader)
    stats, slot = NodeStats(), LatestSlot()

    def bad(text: str) -> None:
        warn(f"msdnet-node: bad message on {cfg.topic}: {text}")

    thread = threading.Thread(target=_receive, args=(reader, waitset, slot, stats, stop, bad), daemon=True)
    thread.start()
    echo(
        f"msdnet-node: serving {cfg.topic} (DDS {in_topic}, domain {cfg.domain_id}) -> {out_name}; "
        f"columns {' '.join(pipe.columns)}"
    )
    handled = 0
    while not stop.is_set():
        item = slot.take(POLL_S)
        if item is None:
            continue
        sample, received_at, index = item
        taken_at = time.perf_counter()
        sec, nsec = stamp_of(sample)
        label = f"message {index} (stamp {sec}.{nsec:09d}, frame {sample.header.frame_id!r})"
        try:
            cloud = message_cloud(sample, pipe.columns, mapping, label)
            res = densify(pipe, cloud, cfg.options)
            writer.write(dense_message(res.points, res.confidence, sample.header))
            with stats.lock:
                stats.published += 1
                now = time.perf_counter()
                stats.latencies.append(now - received_at)
                stats.service.append(now - taken_at)
        except MsdnetError as err:
            with stats.lock:
                stats.bad += 1
            bad(str(err))  # '<label>: <cause>'
        except Exception as err:  # one bad message must not stop the node
            with stats.lock:
                stats.bad += 1
            bad(f"{label}: {type(err).__name__}: {' '.join(str(err).split())[:200]}")
        handled += 1
        if cfg.stats_every and handled % cfg.stats_every == 0:
            echo(stats.line())
    thread.join(timeout=2 * POLL_S)
    dds.close()
    return stats


def write_stats(path: Path, stats: NodeStats) -> None:
    """The final stats as JSON at ``path`` (atomically)."""
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(stats.summary(), indent=1) + "\n", encoding="utf-8")
