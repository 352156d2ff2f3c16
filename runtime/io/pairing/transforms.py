"""Transforms from a bag: static and timed TF edges, the radar-to-LiDAR extrinsic, poses.

TF convention (ROS): a ``TransformStamped`` with ``header.frame_id = P`` and ``child_frame_id = C``
is ``T_P<-C`` (4 x 4, p_P = T p_C). Timed edges (``/tf``, odometry) are interpolated at a stamp
(linear translation, spherical rotation) between the two samples around a stamp when they are at
most ``MAX_BRACKET_NS`` apart; otherwise the nearest sample within ``max_gap_ns``, else none.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from msdnet.runtime.errors import MsdnetError

MAX_BRACKET_NS = 1_000_000_000  # interpolate between two samples at most this far apart


def matrix(translation: Sequence[float], quaternion_xyzw: Sequence[float]) -> np.ndarray:
    """(4, 4) float64 from a translation (3,) and a quaternion (x, y, z, w)."""
    t = np.eye(4)
    t[:3, :3] = Rotation.from_quat(np.asarray(quaternion_xyzw, dtype=np.float64)).as_matrix()
    t[:3, 3] = translation
    return t


def parse_extrinsic(text: str) -> np.ndarray:
    """``"x,y,z,roll,pitch,yaw"`` (metres, radians; the radar's pose in the LiDAR frame, ROS
    fixed-axis roll-pitch-yaw) -> (4, 4) ``T_lidar<-radar``; MsdnetError naming ``--extrinsic``."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 6 or not np.all(np.isfinite(values)):
        raise MsdnetError("--extrinsic", f"expected six numbers x,y,z,roll,pitch,yaw, got {text!r}")
    t = np.eye(4)
    t[:3, :3] = Rotation.from_euler("xyz", values[3:]).as_matrix()
    t[:3, 3] = values[:3]
    return t


def tf_matrix(transform: Any) -> np.ndarray:
    """geometry_msgs/Transform -> (4, 4)."""
    tr, q = transform.translation, transform.rotation
    return matrix((tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w))


def stamp_ns(header: Any) -> int:
    """std_msgs/Header -> nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class TimedEdge:
    """``T_parent<-child`` sampled at stamps; :meth:`at` interpolates."""

    def __init__(self) -> None:
        self.stamps: list[int] = []  # ns, sorted on first use
        self.mats: list[np.ndarray] = []  # (4, 4) each
        self._sorted = True

    def add(self, ns: int, mat: np.ndarray) -> None:
        self._sorted = self._sorted and (not self.stamps or ns >= self.stamps[-1])
        self.stamps.append(ns)
        self.mats.append(mat)

    def at(self, ns: int, max_gap_ns: int) -> np.ndarray | None:
        """The transform at ``ns`` (interpolated), None when no sample lies within ``max_gap_ns``."""
        if not self._sorted:
            order = np.argsort(self.stamps, kind="stable")
            self.stamps = [self.stamps[i] for i in order]
            self.mats = [self.mats[i] for i in order]
            self._sorted = True
        i = bisect.bisect_left(self.stamps, ns)
        lo, hi = max(i - 1, 0), min(i, len(self.stamps) - 1)
        inside = (
            self.stamps[lo] < ns < self.stamps[hi] and self.stamps[hi] - self.stamps[lo] <= MAX_BRACKET_NS
        )
        if not inside:  # at or beyond the ends, or across a long gap: the nearest sample if near
            best = lo if abs(self.stamps[lo] - ns) <= abs(self.stamps[hi] - ns) else hi
            return self.mats[best] if abs(self.stamps[best] - ns) <= max_gap_ns else None
        w = (ns - self.stamps[lo]) / (self.stamps[hi] - self.stamps[lo])
        a, b = self.mats[lo], self.mats[hi]
        out = np.eye(4)
        out[:3, 3] = (1 - w) * a[:3, 3] + w * b[:3, 3]
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))
        out[:3, :3] = slerp([w]).as_matrix()[0]
        return out


class TfTree:
    """Static and timed edges by child frame (each frame has one parent, as in TF)."""

    def __init__(self) -> None:
        self.static: dict[str, tuple[str, np.ndarray]] = {}  # child -> (parent, T_parent<-child)
        self.timed: dict[str, tuple[str, TimedEdge]] = {}  # child -> (parent, samples)

    def add_message(self, msg: Any, static: bool) -> None:
        """One tf2_msgs/TFMessage (``/tf_static`` when ``static``, else ``/tf``)."""
        for tr in msg.transforms:
            parent, child = tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/")
            if static:
                self.static[child] = (parent, tf_matrix(tr.transform))
            else:
                edge = self.timed.setdefault(child, (parent, TimedEdge()))[1]
                edge.add(stamp_ns(tr.header), tf_matrix(tr.transform))

    def add_timed(self, parent: str, child: str, ns: int, mat: np.ndarray) -> None:
        """One timed sample (an odometry message)."""
        self.timed.setdefault(child.lstrip("/"), (parent.lstrip("/"), TimedEdge()))[1].add(ns, mat)

    def to_root(self, frame: str, ns: int | None, max_gap_ns: int) -> tuple[str, np.ndarray, bool] | None:
        """-> (root frame, T_root<-frame, whether a timed edge was used); static edges only when
        ``ns`` is None. None when a timed edge has no sample near ``ns``."""
        frame, t, timed = frame.lstrip("/"), np.eye(4), False
        for _ in range(64):  # TF trees are shallow; this also stops a loop
            if frame in self.static:
                parent, edge = self.static[frame]
            elif ns is not None and frame in self.timed:
                parent, samples = self.timed[frame]
                edge = samples.at(ns, max_gap_ns)
                if edge is None:
                    return None
                timed = True
            else:
                return frame, t, timed
            t, frame = edge @ t, parent
        return None

    def between(self, target: str, source: str) -> np.ndarray | None:
        """Static ``T_target<-source`` when both frames hang from one static root, else None."""
        a, b = self.to_root(target, None, 0), self.to_root(source, None, 0)
        if a is None or b is None or a[0] != b[0]:
            return None
        return np.linalg.inv(a[1]) @ b[1]

    def pose(self, frame: str, ns: int, max_gap_ns: int) -> np.ndarray | None:
        """``T_root<-frame`` at ``ns`` when the path to the root crosses a timed edge (a pose in
        an odometry / map frame), else None."""
        found = self.to_root(frame, ns, max_gap_ns)
        return found[1] if found is not None and found[2] else None
