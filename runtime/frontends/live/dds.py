"""Cyclone DDS entities for ``msdnet-node``: participant, QoS, and a loopback-only configuration.

QoS (what ROS 2 sensor drivers and RViz2 match):

- the subscription is best effort, volatile: it matches a publisher with the ROS 2 sensor-data
  profile (``rclcpp::SensorDataQoS``: best effort, keep last 5) and a reliable one. Its history
  keeps the last ``READER_DEPTH`` samples until the receive thread takes them (history depth is
  not part of QoS matching), so a scan is never lost uncounted while that thread waits for the
  CPU; the node itself keeps one waiting scan (``runtime/frontends/live/node``) and counts the others;
- the ``/dense`` publication is reliable, keep last 1, volatile: RViz2's PointCloud2 display
  (reliable, keep last 5 by default) and best-effort subscribers both match it, and keep-last
  history never blocks the node on a slow subscriber.

Both use XCDR1 (plain CDR), the data representation ROS 2 writes and reads.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from msdnet.runtime.errors import MsdnetError

READER_DEPTH = 8  # samples a reader holds until its thread takes them (history is not matched)
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


def loopback_env(folder: str | Path, env: dict[str, str] | None = None) -> dict[str, str]:
    """Write ``folder/cyclonedds.xml`` (loopback interface, multicast off, 127.0.0.1 the only
    peer) and return ``env`` (default: this process's) with ``CYCLONEDDS_URI`` pointing at it and
    ``ORT_DISABLE_TELEMETRY=1``: for tests and benchmarks, so nothing reaches beyond loopback."""
    path = Path(folder) / "cyclonedds.xml"
    path.write_text(LOOPBACK_XML, encoding="utf-8")
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
    """Keep last ``depth``, volatile, XCDR1; best effort (subscription) or reliable (publication)."""
    _, _, _, qos, _, _, util = cyclonedds()
    rel = qos.Policy.Reliability.Reliable(util.duration(milliseconds=100))
    return qos.Qos(
        rel if reliable else qos.Policy.Reliability.BestEffort,
        qos.Policy.History.KeepLast(depth),
        qos.Policy.Durability.Volatile,
        qos.Policy.DataRepresentation(use_cdrv0_representation=True),
    )


class Endpoints:
    """One participant on ``domain_id`` with a reader and/or a writer of PointCloud2 topics."""

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

    def _topic(self, dds_name: str) -> Any:
        from msdnet.runtime.frontends.live.idl import PointCloud2

        _, _, _, _, _, topic, _ = cyclonedds()
        if dds_name not in self._topics:
            self._topics[dds_name] = topic.Topic(self.participant, dds_name, PointCloud2)
        return self._topics[dds_name]

    def reader(self, dds_name: str, reliable: bool = False, depth: int = READER_DEPTH) -> Any:
        """A PointCloud2 reader of ``dds_name`` (``rt/...``), best effort unless told, keeping the
        last ``depth`` samples until they are taken."""
        _, _, _, _, sub, _, _ = cyclonedds()
        return sub.DataReader(self.participant, self._topic(dds_name), qos=sensor_qos(reliable, depth))

    def writer(self, dds_name: str, reliable: bool = True) -> Any:
        """A keep-last-1 PointCloud2 writer of ``dds_name`` (reliable unless told otherwise)."""
        _, _, pub, _, _, _, _ = cyclonedds()
        return pub.DataWriter(self.participant, self._topic(dds_name), qos=sensor_qos(reliable))

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
