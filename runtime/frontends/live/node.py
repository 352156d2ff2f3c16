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

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.densify import DensifyOptions, densify
from msdnet.runtime.frontends.live.stats import (  # noqa: F401 - the node's stats, as before
    LatestSlot,
    NodeStats,
    engines_used,
    write_stats,
)

POLL_S = 0.05  # how often both threads look at the stop flag (SIGTERM -> exit well within 1 s)
WATCH_S = 0.5  # how often the receive thread looks for writers it cannot match (off the hot path)
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
    node_name: str = "msdnet_node"  # ROS 2 node name: ~/debug topics, diagnostic status name
    namespace: str = "/"  # ROS 2 namespace of the node
    diagnostics_period_s: float = 1.0  # /diagnostics period (diagnostic_updater's), the latest state

    @property
    def dense_topic(self) -> str:
        return self.output_topic or self.topic.rstrip("/") + DENSE_SUFFIX

    @property
    def fqn(self) -> str:
        """The node's fully qualified name, ``/namespace/name``."""
        return "/" + "/".join(t for t in f"{self.namespace}/{self.node_name}".split("/") if t)


def _receive(
    reader: Any,
    waitset: Any,
    slot: LatestSlot,
    stats: NodeStats,
    stop: threading.Event,
    bad: Callable[[str], None],
    type_name: str,
    watch: Any = None,
) -> None:
    """Receive thread: take samples one by one into ``slot`` until ``stop``; between them, let
    ``watch`` (a ``discovery.WriterWatch``) name the writers the reader cannot match."""
    from cyclonedds.util import duration

    index = 0
    watched = 0.0  # monotonic time of the last look at the writers
    while not stop.is_set():
        waitset.wait(duration(seconds=POLL_S))
        if watch is not None and time.monotonic() - watched >= WATCH_S:
            watched = time.monotonic()
            try:
                watch.poll()
            except Exception:  # noqa: BLE001 - naming unmatched writers must never stop the receiving
                watch = None
            else:
                with stats.lock:
                    stats.unmatched_writers = watch.count
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
    stats: NodeStats | None = None,
    serving: Callable[[], bool] | None = None,
) -> NodeStats:
    """Serve ``cfg.topic`` with ``pipe`` until ``stop`` is set; -> the final stats (``stats``, or
    new ones). Prints a ready line once subscribed, a stats line every ``cfg.stats_every``
    messages. ``serving()`` is asked before the first scan (``lifecycle.Lifecycle.serving``):
    False (a signal came while starting) returns at once."""
    from msdnet.runtime.frontends.live.dds import Endpoints
    from msdnet.runtime.frontends.live.discovery import WriterWatch
    from msdnet.runtime.frontends.live.idl import PointCloud2, RadarScan, dds_topic
    from msdnet.runtime.frontends.live.messages import output_message, stamp_of
    from msdnet.runtime.frontends.live.observe import LEVEL_NAMES, Observer

    in_topic = dds_topic(cfg.topic)
    out_name = cfg.dense_topic
    scan = _Scan(pipe, cfg)
    struct = RadarScan if cfg.input_type == "radar_scan" else PointCloud2
    type_name = "RadarScan" if struct is RadarScan else "PointCloud2"
    stats = NodeStats() if stats is None else stats
    pipe.warmup()
    view = None
    if cfg.foxglove:
        from msdnet.runtime.frontends.live.foxglove_view import FoxgloveView

        view = FoxgloveView(cfg.foxglove_host, cfg.foxglove_port, cfg.topic, out_name)
    dds = Endpoints(cfg.domain_id)
    reader = dds.reader(in_topic, reliable=cfg.input_reliable, struct=struct)
    writer = dds.writer(dds_topic(out_name), reliable=cfg.output_reliable)
    observer = Observer(dds, cfg)
    waitset, _cond = dds.waitset(reader)
    slot = LatestSlot()

    def bad(text: str) -> None:
        warn(f"msdnet-node: bad message on {cfg.topic}: {text}")

    def unmatched(text: str) -> None:
        warn(f"msdnet-node: {text}")

    dds_type = struct.__idl__.idl_transformed_typename
    watch = WriterWatch(dds.participant, reader, in_topic, cfg.topic, dds_type, cfg.input_reliable, unmatched)
    if serving is not None and not serving():
        return stats
    thread = threading.Thread(
        target=_receive, args=(reader, waitset, slot, stats, stop, bad, type_name, watch), daemon=True
    )
    thread.start()
    observer.start()
    fox = f"; Foxglove ws://{cfg.foxglove_host}:{view.port}" if view is not None else ""
    echo(
        f"msdnet-node: serving {cfg.topic} (DDS {in_topic}, {type_name}, domain {cfg.domain_id}) -> "
        f"{out_name} as node {cfg.fqn}; columns {' '.join(pipe.columns)}{fox}"
    )
    handled = 0
    noted_nonfinite = False
    previous_start: float | None = None
    while not stop.is_set():
        item = slot.take(POLL_S)
        if item is None:
            continue
        sample, received_at, index = item
        taken_at = time.perf_counter()
        observer.health.begin(time.monotonic())
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
            level = observer.scan(processing_ms, cyclic_ms, latency_ms, time.monotonic())
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
        finally:
            observer.health.begin(None)  # a scan that failed is not running any more
        handled += 1
        if cfg.stats_every and handled % cfg.stats_every == 0:
            echo(stats.line())
    # the other threads first: nothing may use an endpoint while the participant is deleted
    thread.join(timeout=1.0)
    ended = observer.close() and not thread.is_alive()
    if view is not None:
        view.close()
    if ended:
        dds.close()
    return stats
