"""Publish point-cloud files as a ROS 2 PointCloud2 topic, and collect ``/dense`` replies.

    python -m msdnet.runtime.frontends.live.publish SCAN... --topic /radar/points --hz 10 --count 30

A stand-in for a radar driver when trying ``msdnet-node`` without one, and the publisher process
of the tests and of ``msdnet-bench live``: the scans (any ``read_cloud`` format, every column as a
float32 field) are sent in turn, ``--count`` messages ``1 / --hz`` apart on an absolute schedule,
header stamp ``start + i / hz`` (frame ``--frame-id``). ``--bad I`` sends message ``I`` malformed
(its data cut short); ``--nonfinite I`` gives message ``I`` rows with NaN / Inf coordinates;
``--lockstep S`` waits for each reply. ``--log FILE`` writes
``{"sent": [[stamp_ns, monotonic_s], ...]}``. ``--radar-scan`` sends each scan as a
``radar_msgs/msg/RadarScan`` instead (x y z -> range, azimuth, elevation; the 4th and 5th
columns as doppler_velocity and amplitude, see :func:`scan_returns`); ``--reliable`` publishes
with reliable QoS instead of a sensor driver's best effort.
:class:`DenseCollector` is the other end: a reliable reader of ``<topic>/dense``.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from pathlib import Path
from typing import Any

import click
import numpy as np

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.frontends.live.dds import Endpoints
from msdnet.runtime.frontends.live.idl import RadarScan, dds_topic
from msdnet.runtime.frontends.live.messages import (
    cloud_message,
    message_array,
    points_to_polar,
    polar_to_points,
    radar_scan_message,
    stamp_of,
)
from msdnet.runtime.frontends.live.node import DENSE_SUFFIX
from msdnet.runtime.io.atomic import atomic_output
from msdnet.runtime.io.files import read_cloud

START_NS = 1_700_000_000 * 10**9  # header stamp of message 0
NONFINITE_ROWS = 4  # rows made NaN / Inf in a --nonfinite message
MATCH_TIMEOUT_S = 20.0  # how long to wait for a subscriber before giving up


def wait_matched(count: Any, what: str, timeout: float = MATCH_TIMEOUT_S) -> None:
    """Wait until ``count()`` (matched endpoints) >= 1; MsdnetError naming ``what`` on timeout."""
    end = time.monotonic() + timeout
    while not count():
        if time.monotonic() > end:
            raise MsdnetError(what, f"no DDS peer matched within {timeout:.0f} s")
        time.sleep(0.02)


def scan_returns(points: np.ndarray, columns: tuple[str, ...], velocity: str, amplitude: str) -> np.ndarray:
    """A cloud (N, C) -> RadarScan returns (N, 5): x y z in polar form, doppler_velocity from
    column ``velocity`` and amplitude from column ``amplitude`` (0 where absent)."""
    table = np.zeros((points.shape[0], 5), np.float32)
    table[:, :3] = points[:, :3]
    for i, name in ((3, velocity), (4, amplitude)):
        if name in columns:
            table[:, i] = points[:, columns.index(name)]
    return points_to_polar(table)


def radar_scan_pair(
    points: np.ndarray, columns: tuple[str, ...], velocity: str, amplitude: str
) -> tuple[np.ndarray, np.ndarray]:
    """-> (the RadarScan returns of a cloud, the same returns as the node reads them: (N, 5)
    [x y z v_r amplitude]); a PointCloud2 of the second is the same scan as the first."""
    returns = scan_returns(points, columns, velocity, amplitude)
    return returns, polar_to_points(returns)


def publish_scans(
    files: list[Path],
    topic: str,
    domain_id: int,
    hz: float,
    count: int,
    frame_id: str = "radar",
    bad: tuple[int, ...] = (),
    start_ns: int = START_NS,
    lockstep: float = 0.0,
    radar_scan: bool = False,
    reliable: bool = False,
    velocity: str = "v_r",
    amplitude: str = "rcs",
    nonfinite: tuple[int, ...] = (),
) -> list[tuple[int, float]]:
    """Send ``count`` scans (cycling through ``files``) at ``hz``; -> [(stamp_ns, monotonic send
    time)] per message. Waits for a subscriber first. ``lockstep`` > 0: after each good message
    wait up to that many seconds for its ``/dense`` reply before the next (no drop however slow
    the node is: the tests' mode on a loaded machine). ``radar_scan``: send RadarScan messages
    (``velocity`` / ``amplitude``: the columns of the doppler velocity and the amplitude).
    ``nonfinite``: messages whose first ``NONFINITE_ROWS`` rows get a NaN or Inf coordinate."""
    clouds = [read_cloud(f) for f in files]
    returns = [scan_returns(c.points, c.columns, velocity, amplitude) for c in clouds] if radar_scan else []
    dds = Endpoints(domain_id)
    struct = RadarScan if radar_scan else None
    writer = dds.writer(dds_topic(topic), reliable=reliable, struct=struct)  # best effort: as a driver
    replies = DenseCollector(topic, domain_id, keep_points=False) if lockstep else None
    wait_matched(writer.get_matched_subscriptions, topic)
    if replies is not None:
        replies.wait_matched()
    time.sleep(0.3)  # the subscriber also needs to have discovered this writer
    sent: list[tuple[int, float]] = []
    t0 = time.monotonic()
    for i in range(count):
        cloud = clouds[i % len(clouds)]
        ns = start_ns + round(i * 1e9 / hz)
        points = cloud.points
        if i in nonfinite:
            points = points.copy()
            points[: NONFINITE_ROWS - 1, 0] = np.nan
            points[NONFINITE_ROWS - 1, 2] = np.inf
        if radar_scan:
            table = returns[i % len(clouds)]
            if i in nonfinite:
                table = scan_returns(points, cloud.columns, velocity, amplitude)
            msg = radar_scan_message(table, divmod(ns, 10**9), frame_id)
        else:
            msg = cloud_message(points, cloud.columns, divmod(ns, 10**9), frame_id)
        if i in bad and radar_scan:  # malformed: a NaN range in every return
            msg = dataclasses.replace(msg, returns=msg.returns.copy())
            msg.returns[:, 0] = np.nan
        elif i in bad:  # malformed: the data holds half the rows the header claims
            msg = dataclasses.replace(msg, data=msg.data[: len(msg.data) // 2])
        delay = t0 + i / hz - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        writer.write(msg)
        sent.append((ns, time.monotonic()))
        if replies is not None and i not in bad:
            replies.wait_for(len(sent) - len([b for b in bad if b < i]), lockstep)
            t0 = time.monotonic() - (i + 1) / hz  # the schedule restarts after the reply
    if replies is not None:
        replies.close()
    time.sleep(0.2)  # let the last sample leave before the participant goes
    return sent


class DenseCollector:
    """A reader of ``<topic>/dense`` (reliable unless told; a reliable reader does not match a
    best-effort writer) collecting (stamp_ns, monotonic receive time,
    (M, 4) float32 [x, y, z, confidence]) in a background thread."""

    def __init__(self, topic: str, domain_id: int, keep_points: bool = True, reliable: bool = True) -> None:
        self.dds = Endpoints(domain_id)
        self.reader = self.dds.reader(dds_topic(topic.rstrip("/") + DENSE_SUFFIX), reliable=reliable)
        self.keep_points = keep_points  # False: keep stamps and times only (long benchmarks)
        self.received: list[tuple[int, float, np.ndarray | None]] = []
        self.frames: list[str] = []  # header.frame_id of each received cloud
        self.fields: list[tuple[str, ...]] = []  # field names of each received cloud
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def wait_matched(self, timeout: float = MATCH_TIMEOUT_S) -> None:
        """Wait until the node's ``/dense`` writer is matched."""
        wait_matched(self.reader.get_matched_publications, "the node's /dense topic", timeout)

    def _run(self) -> None:
        from cyclonedds.util import duration

        ws, _cond = self.dds.waitset(self.reader)
        while not self._stop.is_set():
            ws.wait(duration(milliseconds=50))
            for sample in self.reader.take(N=64):
                if not sample.sample_info.valid_data:
                    continue
                sec, nsec = stamp_of(sample)
                pts = message_array(sample) if self.keep_points else None
                self.frames.append(sample.header.frame_id)
                self.fields.append(tuple(f.name for f in sample.fields))
                self.received.append((sec * 10**9 + nsec, time.monotonic(), pts))

    def wait_for(self, n: int, timeout: float) -> bool:
        """Wait until ``n`` clouds arrived (True) or ``timeout`` seconds passed (False)."""
        end = time.monotonic() + timeout
        while len(self.received) < n and time.monotonic() < end:
            time.sleep(0.02)
        return len(self.received) >= n

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("files", nargs=-1, required=True, type=click.Path(path_type=Path, exists=True))
@click.option("--topic", default="/radar/points", show_default=True)
@click.option("--domain-id", type=click.IntRange(0, 232), default=0, show_default=True)
@click.option("--hz", type=click.FloatRange(min=0.1), default=10.0, show_default=True)
@click.option("--count", type=click.IntRange(min=1), help="Messages to send [one per file].")
@click.option("--frame-id", default="radar", show_default=True)
@click.option("--bad", type=int, multiple=True, help="Send message I malformed (data cut short).")
@click.option("--start-ns", type=int, default=START_NS, show_default=True, help="Stamp of message 0.")
@click.option("--log", type=click.Path(path_type=Path), help="Write the send times as JSON here.")
@click.option("--lockstep", type=float, default=0.0, help="Wait up to S seconds for each reply.")
@click.option("--nonfinite", type=int, multiple=True, help="Give message I rows with NaN / Inf.")
@click.option("--radar-scan", is_flag=True, help="Send radar_msgs/msg/RadarScan messages.")
@click.option("--reliable", is_flag=True, help="Reliable QoS (default: best effort, as a driver).")
@click.option("--velocity", default="v_r", show_default=True, help="RadarScan: doppler_velocity column.")
@click.option("--amplitude", default="rcs", show_default=True, help="RadarScan: amplitude column.")
@one_line_errors
def main(
    files: tuple[Path, ...],
    topic: str,
    domain_id: int,
    hz: float,
    count: int | None,
    frame_id: str,
    bad: tuple[int, ...],
    start_ns: int,
    log: Path | None,
    lockstep: float,
    radar_scan: bool,
    reliable: bool,
    velocity: str,
    amplitude: str,
    nonfinite: tuple[int, ...],
) -> None:
    """Publish point-cloud files as a PointCloud2 (or RadarScan) topic over DDS."""
    n = count or len(files)
    sent = publish_scans(
        list(files),
        topic,
        domain_id,
        hz,
        n,
        frame_id,
        bad,
        start_ns,
        lockstep,
        radar_scan,
        reliable,
        velocity,
        amplitude,
        nonfinite,
    )
    if log is not None:
        with atomic_output(log) as tmp:
            Path(tmp).write_text(json.dumps({"sent": sent}) + "\n", encoding="utf-8")
    click.echo(f"published {len(sent)} messages on {topic} at {hz:g} Hz")


if __name__ == "__main__":
    main()
