"""Cyclone DDS entities for ``msdnet-node``: participant, QoS, and a loopback-only configuration.

QoS (what ROS 2 sensor drivers and RViz2 match):

- the subscription is ROS 2's sensor-data profile (``rclcpp::SensorDataQoS``: best effort,
  volatile, keep last ``READER_DEPTH`` = 5): it matches best-effort publishers (sensor drivers)
  and reliable ones alike. The receive thread takes every sample as it arrives; the node itself
  keeps one waiting scan (``runtime/frontends/live/node``) and counts the others;
- the dense publication is reliable (a parameter: ``output_reliability``), keep last 1,
  volatile: RViz2's PointCloud2 display (reliable, keep last 5 by default) and best-effort
  subscribers both match a reliable writer, and keep-last history never blocks the node on a
  slow subscriber;
- the debug topics and ``/diagnostics`` are reliable, volatile, keep last 1, as Autoware's debug
  publishers and ``diagnostic_updater`` write them.

Both use XCDR1 (plain CDR), the data representation ROS 2 writes and reads.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from msdnet.runtime.errors import MsdnetError

READER_DEPTH = 5  # sensor-data QoS: keep last 5 (history depth is not part of QoS matching)
MAX_DOMAIN_ID = 232  # Cyclone: the ports of higher domain ids overflow (7400 + 250 * id)
LOOPBACK_XML = """<?xml version="1.0" encoding="UTF-8"?>
<CycloneDDS xmlns="https://cdds.io/config">
  <Domain id="any">
    <General>
      <Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>
      <AllowMulticast>false</AllowMulticast>
    </General>
    <Discovery>
      <Peers><Peer address="127.0.0.1"/></Peers>
      <ParticipantIndex>auto</ParticipantIndex>
      <MaxAutoParticipantIndex>20</MaxAutoParticipantIndex>
    </Discovery>
  </Domain>
</CycloneDDS>
"""


def cyclonedds() -> Any:
    """The cyclonedds modules; MsdnetError with the install line when the extra is missing."""
    try:
        import cyclonedds  # noqa: F401
    except ImportError:
        raise MsdnetError("msdnet-node", "needs the cyclonedds package: pip install 'msdnet[live]'") from None
    from cyclonedds import core, domain, pub, qos, sub, topic, util

    return core, domain, pub, qos, sub, topic, util


def loopback_env(
    folder: str | Path, env: dict[str, str] | None = None, socket_buffer: str | None = None
) -> dict[str, str]:
    """Write ``folder/cyclonedds.xml`` (loopback interface, multicast off, 127.0.0.1 the only
    peer) and return ``env`` (default: this process's) with ``CYCLONEDDS_URI`` pointing at it and
    ``ORT_DISABLE_TELEMETRY=1``: for tests and benchmarks, so nothing reaches beyond loopback.
    ``socket_buffer`` (e.g. ``"4MiB"``): the UDP receive and send buffers Cyclone asks for (the
    kernel caps them at net.core.rmem_max / wmem_max), for messages of many megabytes."""
    path = Path(folder) / "cyclonedds.xml"
    xml = LOOPBACK_XML
    if socket_buffer:
        internal = (
            f'    <Internal>\n      <SocketReceiveBufferSize max="{socket_buffer}"/>\n'
            f'      <SocketSendBufferSize max="{socket_buffer}"/>\n    </Internal>\n'
        )
        xml = xml.replace("  </Domain>", internal + "  </Domain>")
    path.write_text(xml, encoding="utf-8")
    out = dict(os.environ if env is None else env)
    out["CYCLONEDDS_URI"] = path.resolve().as_uri()
    out["ORT_DISABLE_TELEMETRY"] = "1"
    return out


def check_domain(domain_id: int) -> int:
    """``domain_id`` if Cyclone can use it, else MsdnetError naming ``--domain-id``."""
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise MsdnetError("--domain-id", f"must be 0..{MAX_DOMAIN_ID}, got {domain_id}")
    return domain_id


def sensor_qos(reliable: bool, depth: int = 1) -> Any:
    """Keep last ``depth``, volatile, XCDR1; best effort or reliable."""
    _, _, _, qos, _, _, util = cyclonedds()
    rel = qos.Policy.Reliability.Reliable(util.duration(milliseconds=100))
    return qos.Qos(
        rel if reliable else qos.Policy.Reliability.BestEffort,
        qos.Policy.History.KeepLast(depth),
        qos.Policy.Durability.Volatile,
        qos.Policy.DataRepresentation(use_cdrv0_representation=True),
    )


class Endpoints:
    """One participant on ``domain_id`` with readers and writers of ROS 2 message topics."""

    def __init__(self, domain_id: int) -> None:
        _, domain, _, _, _, _, _ = cyclonedds()
        try:
            self.participant = domain.DomainParticipant(check_domain(domain_id))
        except Exception as err:  # a broken CYCLONEDDS_URI, no usable interface
            cause = " ".join(str(err).split())[:200]
            raise MsdnetError(
                f"DDS domain {domain_id}", f"cannot join: {cause} (check CYCLONEDDS_URI)"
            ) from None
        self._topics: dict[str, Any] = {}

    def _topic(self, dds_name: str, struct: Any = None) -> Any:
        from msdnet.runtime.frontends.live.idl import PointCloud2

        _, _, _, _, _, topic, _ = cyclonedds()
        if dds_name not in self._topics:
            self._topics[dds_name] = topic.Topic(self.participant, dds_name, struct or PointCloud2)
        return self._topics[dds_name]

    def reader(
        self, dds_name: str, reliable: bool = False, depth: int = READER_DEPTH, struct: Any = None
    ) -> Any:
        """A reader of ``dds_name`` (``rt/...``; ``struct`` default PointCloud2), best effort unless
        told, keeping the last ``depth`` samples until they are taken."""
        _, _, _, _, sub, _, _ = cyclonedds()
        topic = self._topic(dds_name, struct)
        return sub.DataReader(self.participant, topic, qos=sensor_qos(reliable, depth))

    def writer(self, dds_name: str, reliable: bool = True, struct: Any = None, depth: int = 1) -> Any:
        """A keep-last-``depth`` writer of ``dds_name`` (``struct`` default PointCloud2), reliable
        unless told otherwise."""
        _, _, pub, _, _, _, _ = cyclonedds()
        topic = self._topic(dds_name, struct)
        return pub.DataWriter(self.participant, topic, qos=sensor_qos(reliable, depth))

    def waitset(self, reader: Any) -> tuple[Any, Any]:
        """(WaitSet, ReadCondition) that wakes when ``reader`` has samples."""
        core, _, _, _, _, _, _ = cyclonedds()
        cond = core.ReadCondition(reader, core.SampleState.Any | core.ViewState.Any | core.InstanceState.Any)
        ws = core.WaitSet(self.participant)
        ws.attach(cond)
        return ws, cond

    def close(self) -> None:
        """Delete the participant and everything in it now (peers see the endpoints go)."""
        self.participant.__del__()  # idempotent in cyclonedds: a second delete is a no-op
