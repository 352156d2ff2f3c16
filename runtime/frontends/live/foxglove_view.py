"""``msdnet-node --foxglove``: the radar and dense clouds served to Foxglove over WebSocket.

The ``foxglove-sdk`` package (``pip install 'msdnet[live]'``) runs a Foxglove WebSocket server
(bound to ``foxglove_host``, 127.0.0.1 by default) with two ``foxglove.PointCloud`` channels
named after the ROS topics: the radar scan as the model sees it (x y z and the model's other
columns) and the dense output (x y z confidence, plus the kept radar fields). Open Foxglove,
connect to ``ws://127.0.0.1:8765`` and add a 3D panel. Each message is logged with the input's
stamp and frame (or the target frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from msdnet.runtime.errors import MsdnetError


def _foxglove() -> Any:
    try:
        import foxglove
    except ImportError:
        raise MsdnetError(
            "--foxglove", "needs the foxglove-sdk package: pip install 'msdnet[live]'"
        ) from None
    return foxglove


class FoxgloveView:
    """A Foxglove server with a radar and a dense PointCloud channel."""

    def __init__(self, host: str, port: int, radar_topic: str, dense_topic: str) -> None:
        foxglove = _foxglove()
        from foxglove.channels import PointCloudChannel

        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(
                name="msdnet-node", host=host, port=port, context=self.context
            )
        except Exception as err:  # port in use, address not here
            cause = " ".join(str(err).split())[:200]
            host_fault = any(k in cause.lower() for k in ("lookup", "assign requested address"))
            flag = "--foxglove-host" if host_fault else "--foxglove-port"  # else in use, not allowed
            raise MsdnetError(flag, f"cannot serve on {host}:{port}: {cause}") from None
        self.radar = PointCloudChannel(radar_topic, context=self.context)
        self.dense = PointCloudChannel(dense_topic, context=self.context)
        self.port = int(self.server.port)

    @staticmethod
    def _message(points: np.ndarray, names: Sequence[str], stamp: tuple[int, int], frame_id: str) -> Any:
        from foxglove.messages import (
            PackedElementField,
            PackedElementFieldNumericType,
            PointCloud,
            Pose,
            Quaternion,
            Timestamp,
            Vector3,
        )

        data = np.ascontiguousarray(points, dtype="<f4")
        fields = [
            PackedElementField(name=n, offset=4 * i, type=PackedElementFieldNumericType.Float32)
            for i, n in enumerate(names)
        ]
        pose = Pose(position=Vector3(x=0, y=0, z=0), orientation=Quaternion(x=0, y=0, z=0, w=1))
        return PointCloud(
            timestamp=Timestamp(sec=stamp[0], nsec=stamp[1]),
            frame_id=frame_id,
            pose=pose,
            point_stride=4 * len(names),
            fields=fields,
            data=data.tobytes(),
        )

    def log(
        self,
        radar: tuple[np.ndarray, Sequence[str]],
        dense: tuple[np.ndarray, Sequence[str]],
        stamp: tuple[int, int],
        radar_frame: str,
        dense_frame: str,
    ) -> None:
        """Log one scan's radar cloud (its own frame) and dense cloud (the output frame)."""
        self.radar.log(self._message(*radar, stamp, radar_frame))
        self.dense.log(self._message(*dense, stamp, dense_frame))

    def close(self) -> None:
        self.server.stop()
