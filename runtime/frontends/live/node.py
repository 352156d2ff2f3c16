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

from msdnet.runtime.engine.pointcloud import DROP_REASONS
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.densify import DensifyOptions, densify
from msdnet.runtime.io.atomic import atomic_output

LATENCY_WINDOW = 100_000  # latencies kept for the percentiles (bounded memory)
SCAN_WINDOW = 1000  # scans whose own input point counts the stats JSON keeps
POLL_S = 0.05  # how often both threads look at the stop flag (SIGTERM -> exit well within 1 s)
DENSE_SUFFIX = "/dense"  # output topic = input topic + this


@dataclass(frozen=True)
class NodeConfig:
    """What one ``msdnet-node`` serves, and how (the parameters: ``runtime/frontends/live/params``)."""

    topic: str  # ROS 2 topic of the radar scans, e.g. /radar/points (DDS rt/radar/points)
    domain_id: int = 0  # DDS domain id: the ROS_DOMAIN_ID of the ROS 2 system
    fields: tuple[str, ...] = ()  # --field model_column=msg_field overrides (as the bag mode)
    options: DensifyOptions = DensifyOptions()  # steps, threshold, seed, keep_radar: as file mode
    stats_every: int = 0  # print a stats line every N handled messages; 0: only at exit
    stats_json: Path | None = None  # also write the final stats here as JSON (atomic), if set
    input_type: str = "pointcloud2"  # or "radar_scan" (radar_msgs/msg/RadarScan)
    input_reliable: bool = False  # reliable subscriber (large messages); default sensor-data best effort
    output_topic: str = ""  # empty: topic + DENSE_SUFFIX
    field_preset: str = ""  # PointCloud2 field layout (messages.PRESETS), empty: by name
    target_frame: str = ""  # publish in this frame (with extrinsic); empty: the input's frame
    extrinsic: tuple[float, ...] | None = None  # x, y, z, roll, pitch, yaw: radar in target_frame
    output_reliable: bool = True  # dense publisher reliability
    publish_debug: bool = True  # ~/debug/*_ms topics (runtime/frontends/live/observe)
    debug_msgs_type: str = "autoware_internal_debug_msgs"  # or tier4_debug_msgs
    publish_diagnostics: bool = True  # /diagnostics
    max_allowed_processing_time_ms: float = 100.0  # WARN above
    max_acceptable_consecutive_delay_ms: float = 1000.0  # ERROR after this long above
    foxglove: bool = False  # serve both clouds to Foxglove (runtime/frontends/live/foxglove_view)
    foxglove_host: str = "127.0.0.1"
    foxglove_port: int = 8765
    testing_delay: tuple[int, int, float] | None = None  # (start, stop, ms): slow scans start..stop-1

    @property
    def dense_topic(self) -> str:
        return self.output_topic or self.topic.rstrip("/") + DENSE_SUFFIX


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


def _receive(
    reader: Any,
    waitset: Any,
    slot: LatestSlot,
    stats: NodeStats,
    stop: threading.Event,
    bad: Callable[[str], None],
    type_name: str,
) -> None:
    """Receive thread: take samples one by one into ``slot`` until ``stop``."""
    from cyclonedds.util import duration

    index = 0
    while not stop.is_set():
        waitset.wait(duration(seconds=POLL_S))
        while not stop.is_set():
            try:
                samples = reader.take(N=1)
            except Exception as err:  # a sample whose bytes do not decode as the type
                with stats.lock:
                    stats.bad += 1
                bad(f"message {index}: cannot decode as a {type_name}: {' '.join(str(err).split())[:160]}")
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


class _Scan:
    """One scan through the node: read, densify, output table (used by :func:`serve`)."""

    def __init__(self, pipe: Any, cfg: NodeConfig) -> None:
        from msdnet.runtime.io.rosbag import parse_field_map

        self.pipe, self.cfg = pipe, cfg
        self.mapping = parse_field_map(cfg.fields, pipe.columns)
        self.transform = None
        if cfg.extrinsic is not None:
            from msdnet.runtime.io.pairing.transforms import parse_extrinsic

            self.transform = parse_extrinsic(",".join(repr(v) for v in cfg.extrinsic))

    def read(self, sample: Any, label: str) -> tuple[Any, tuple[str, ...]]:
        from msdnet.runtime.frontends.live.messages import message_cloud, radar_scan_cloud

        if self.cfg.input_type == "radar_scan":
            return radar_scan_cloud(sample, self.pipe.columns, self.mapping, label)
        return message_cloud(sample, self.pipe.columns, self.mapping, label, self.cfg.field_preset or None)

    def output(self, cloud: Any, res: Any, names: tuple[str, ...]) -> tuple[np.ndarray, tuple[str, ...]]:
        """-> (output table, its field names): x y z confidence (+ the kept radar fields)."""
        from msdnet.runtime.engine.voxelize import in_range_mask
        from msdnet.runtime.frontends.live.messages import output_names, output_table
        from msdnet.runtime.io.files import DENSE_COLUMNS

        if not self.cfg.options.keep_radar:
            return output_table(res.points, res.confidence, None, self.transform), DENSE_COLUMNS
        pts = self.pipe.select_columns(cloud)
        kept = pts[in_range_mask(pts, self.pipe.artifact.grid)][:, 3:]  # the rows keep_radar appended
        if kept.shape[0] != res.stats.get("radar_kept", kept.shape[0]):
            raise RuntimeError(f"kept {kept.shape[0]} radar rows, the pipeline {res.stats['radar_kept']}")
        table = output_table(res.points, res.confidence, kept, self.transform)
        return table, output_names(names[3:])


def _testing_delay(cfg: NodeConfig, handled: int) -> None:
    if cfg.testing_delay is not None:
        first, stop, ms = cfg.testing_delay
        if first <= handled < stop:
            time.sleep(ms / 1e3)


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
    from msdnet.runtime.frontends.live.idl import PointCloud2, RadarScan, dds_topic
    from msdnet.runtime.frontends.live.messages import output_message, stamp_of
    from msdnet.runtime.frontends.live.observe import LEVEL_NAMES, Observer

    in_topic = dds_topic(cfg.topic)
    out_name = cfg.dense_topic
    scan = _Scan(pipe, cfg)
    struct = RadarScan if cfg.input_type == "radar_scan" else PointCloud2
    type_name = "RadarScan" if struct is RadarScan else "PointCloud2"
    pipe.warmup()
    view = None
    if cfg.foxglove:
        from msdnet.runtime.frontends.live.foxglove_view import FoxgloveView

        view = FoxgloveView(cfg.foxglove_host, cfg.foxglove_port, cfg.topic, out_name)
    dds = Endpoints(cfg.domain_id)
    reader = dds.reader(in_topic, reliable=cfg.input_reliable, struct=struct)
    writer = dds.writer(dds_topic(out_name), reliable=cfg.output_reliable)
    observer = Observer(dds, cfg, hardware_id=f"msdnet_node {cfg.topic}")
    waitset, _cond = dds.waitset(reader)
    stats, slot = NodeStats(), LatestSlot()

    def bad(text: str) -> None:
        warn(f"msdnet-node: bad message on {cfg.topic}: {text}")

    thread = threading.Thread(
        target=_receive, args=(reader, waitset, slot, stats, stop, bad, type_name), daemon=True
    )
    thread.start()
    fox = f"; Foxglove ws://{cfg.foxglove_host}:{view.port}" if view is not None else ""
    echo(
        f"msdnet-node: serving {cfg.topic} (DDS {in_topic}, {type_name}, domain {cfg.domain_id}) -> "
        f"{out_name}; columns {' '.join(pipe.columns)}{fox}"
    )
    handled = 0
    noted_nonfinite = False
    previous_start: float | None = None
    while not stop.is_set():
        item = slot.take(POLL_S)
        if item is None:
            observer.idle(time.perf_counter())
            continue
        sample, received_at, index = item
        taken_at = time.perf_counter()
        cyclic_ms = None if previous_start is None else (taken_at - previous_start) * 1e3
        previous_start = taken_at
        sec, nsec = stamp_of(sample)
        label = f"message {index} (stamp {sec}.{nsec:09d}, frame {sample.header.frame_id!r})"
        try:
            cloud, names = scan.read(sample, label)
            _testing_delay(cfg, handled)
            res = densify(pipe, cloud, cfg.options)
            table, out_names = scan.output(cloud, res, names)
            frame = cfg.target_frame or sample.header.frame_id
            writer.write(output_message(table, out_names, sample.header, frame))
            now = time.perf_counter()
            processing_ms = (now - taken_at) * 1e3
            latency_ms = (time.time_ns() - (sec * 10**9 + nsec)) / 1e6
            with stats.lock:
                stats.published += 1
                stats.latencies.append(now - received_at)
                stats.service.append(now - taken_at)
                stats.pipeline_latency_ms.append(latency_ms)
                if cyclic_ms is not None:
                    stats.cyclic_ms.append(cyclic_ms)
            stats.add_scan(f"{sec}.{nsec:09d}", res.stats)
            level = observer.scan(processing_ms, cyclic_ms, latency_ms, now)
            with stats.lock:
                stats.diagnostics[LEVEL_NAMES[level]] += 1
            if cloud.dropped_nonfinite and not noted_nonfinite:
                noted_nonfinite = True
                warn(
                    f"msdnet-node: note: {label}: {cloud.dropped_nonfinite} points with NaN/Inf dropped "
                    "(this and later drops are counted in the stats line and --stats-json)"
                )
            if view is not None:
                kept = (cloud.points, cloud.columns)
                view.log(kept, (table, out_names), (sec, nsec), sample.header.frame_id, frame)
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
    if view is not None:
        view.close()
    dds.close()
    return stats


def write_stats(path: Path, stats: NodeStats, engines: dict[str, Any] | None = None) -> None:
    """The final stats as JSON at ``path`` (atomically); ``engines``: what ``engines_used`` says."""
    body = stats.summary() | ({} if engines is None else {"engines": engines})
    with atomic_output(path) as tmp:
        Path(tmp).write_text(json.dumps(body, indent=1) + "\n", encoding="utf-8")


def engines_used(pipe: Any, provider: str) -> dict[str, Any]:
    """The provider asked for, the engine each graph runs on and the head graph, as JSON:
    ``{"provider": str, "graphs": {file: engine}, "head": "dense" | "coarse-to-fine" | None}``."""
    auto = getattr(pipe, "auto", None)
    if auto is None:  # a provider by name: every graph on it
        return {"provider": provider, "graphs": {}, "head": None}
    graphs = {f: pick.engine for f, pick in auto.picks.items()}
    return {"provider": provider, "graphs": graphs, "head": None if auto.head is None else auto.head.head}
