"""A point cloud with named columns: the one container every reader returns.

Column names are lower-case canonical names: ``x y z`` first by convention, then e.g.
``rcs v_r v_r_compensated time`` (VoD radar), ``intensity`` (KITTI/VoD LiDAR), ``v_r mag``
(Astyx radar), ``reflectivity laser_id timestamp`` (Astyx LiDAR). Coordinates are metres.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from msdnet.runtime.errors import MsdnetError

XYZ = ("x", "y", "z")
# the input rows the engine does not use, by reason: Result.stats / summary keys -> printed words
DROP_REASONS = {
    "dropped_nonfinite": "with NaN/Inf",
    "dropped_outside_grid": "outside the grid",
    "dropped_over_cap": "over the voxel cap",
}


def canonical_column(name: str) -> str:
    """``"LaserID"`` -> ``"laser_id"``, ``"V_r"`` -> ``"v_r"``, ``"RCS"`` -> ``"rcs"``."""
    snake = re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", name.strip())  # camelCase boundaries
    return re.sub(r"[^0-9a-z_]+", "_", snake.lower()).strip("_")


@dataclass(frozen=True, eq=False)
class PointCloud:
    """``points``: (N, C) float32, one row per point; ``columns``: the C column names."""

    points: np.ndarray  # (N, C) float32, C == len(columns)
    columns: tuple[str, ...]  # lower-case canonical column names, must contain x y z
    dropped_nonfinite: int = 0  # rows with NaN/Inf removed when the cloud was loaded
    source: str | None = None  # file the cloud came from, if any

    def __post_init__(self) -> None:
        pts = np.asarray(self.points)
        if pts.ndim != 2 or pts.shape[1] != len(self.columns):
            raise ValueError(
                f"points must be (N, {len(self.columns)}) for columns {self.columns}, got shape {pts.shape}"
            )
        if pts.dtype != np.float32:
            pts = pts.astype(np.float32)
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "columns", tuple(self.columns))
        if len(set(self.columns)) != len(self.columns):
            raise ValueError(f"duplicate column names: {self.columns}")
        missing = [c for c in XYZ if c not in self.columns]
        if missing:
            raise MsdnetError(self.source, f"point cloud has no {'/'.join(missing)} column")

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def xyz(self) -> np.ndarray:
        """(N, 3) float32 [x, y, z]."""
        if self.columns[:3] == XYZ:
            return self.points[:, :3]
        return self.points[:, [self.columns.index(c) for c in XYZ]]

    def has(self, name: str) -> bool:
        """Whether a column of that name exists."""
        return name in self.columns

    def column(self, name: str) -> np.ndarray:
        """(N,) float32: one column by name; MsdnetError naming it when missing."""
        if name not in self.columns:
            raise MsdnetError(self.source, f"no column {name!r} (has {' '.join(self.columns)})")
        return self.points[:, self.columns.index(name)]

    def select(self, names: Sequence[str]) -> PointCloud:
        """A cloud with only ``names``, in that order; MsdnetError naming a missing column."""
        idx = []
        for name in names:
            if name not in self.columns:
                raise MsdnetError(self.source, f"no column {name!r} (has {' '.join(self.columns)})")
            idx.append(self.columns.index(name))
        return replace(self, points=self.points[:, idx], columns=tuple(names))

    def subset(self, mask_or_index: np.ndarray) -> PointCloud:
        """The rows picked by a boolean (N,) mask or an integer index array."""
        return replace(self, points=self.points[mask_or_index])

    def transformed(self, transform: np.ndarray) -> PointCloud:
        """Rigid transform of x y z by a (4, 4) matrix (p' = R p + t); other columns untouched."""
        t = np.asarray(transform, dtype=np.float64)
        if t.shape != (4, 4):
            raise ValueError(f"transform must be (4, 4), got {t.shape}")
        pts = self.points.copy()
        moved = transform_xyz(self.xyz, t)  # (N, 3) float64
        for i, c in enumerate(XYZ):
            pts[:, self.columns.index(c)] = moved[:, i]
        return replace(self, points=pts)


def transform_xyz(xyz: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """xyz: (N, 3) [x, y, z] -> (N, 3) float64 ``R p + t`` for a (4, 4) rigid transform.

    Written per output column: several times faster here than ``xyz @ R.T`` with N x 3 shapes.
    """
    t = np.asarray(transform, dtype=np.float64)
    p = np.asarray(xyz)
    out = np.empty((len(p), 3), dtype=np.float64)
    for i in range(3):
        out[:, i] = p[:, 0] * t[i, 0] + p[:, 1] * t[i, 1] + p[:, 2] * t[i, 2] + t[i, 3]
    return out


def concat_clouds(clouds: Sequence[PointCloud]) -> PointCloud:
    """Stack clouds with identical columns (rows in order); counts of dropped rows add up."""
    if not clouds:
        raise ValueError("concat_clouds needs at least one cloud")
    cols = clouds[0].columns
    for c in clouds[1:]:
        if c.columns != cols:
            raise ValueError(f"column mismatch: {cols} vs {c.columns}")
    return PointCloud(
        np.concatenate([c.points for c in clouds], axis=0),
        cols,
        dropped_nonfinite=sum(c.dropped_nonfinite for c in clouds),
        source=clouds[0].source,
    )
