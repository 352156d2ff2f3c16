"""Decoding thresholds by range band (manifest ``range_thresholds``).

The head's occupancy means less far away: the LiDAR the model learned from is dense near the
sensor and sparse at 30 m, so one occupancy threshold decodes too few points near and too many far
(measured on the Astyx selection slice, docs/quality.md). A model folder may therefore give one
threshold per band of horizontal range ``r = sqrt(x^2 + y^2)`` (metres, radar frame) of each
decoded point:

    band 0: r < edges_m[0],  band k: edges_m[k-1] <= r < edges_m[k],  last band: r >= edges_m[-1]

The decoder compares each voxel's occupancy with its point's band threshold as it decodes
(``decode._passes``): the same points as decoding at each band's threshold and keeping that band's,
since a voxel's occupancy and offset do not depend on the threshold (r compared as x^2 + y^2
against the squared edges, in float64). ``msdnet-export bands`` chooses them on the
selection slice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.errors import MsdnetError


@dataclass(frozen=True)
class RangeThresholds:
    """One occupancy threshold per band of horizontal range."""

    edges_m: tuple[float, ...]  # band edges, metres, strictly increasing, > 0
    thresholds: tuple[float, ...]  # one per band (len(edges_m) + 1), each in (0, 1)

    def __post_init__(self) -> None:
        edges, thr = self.edges_m, self.thresholds
        if len(thr) != len(edges) + 1:
            raise ValueError(f"{len(edges)} edges need {len(edges) + 1} thresholds, got {len(thr)}")
        if any(not math.isfinite(e) or e <= 0.0 for e in edges) or any(
            b <= a for a, b in zip(edges, edges[1:], strict=False)
        ):
            raise ValueError(f"edges_m must be finite, > 0 and strictly increasing, got {list(edges)}")
        if any(not math.isfinite(t) or not 0.0 < t < 1.0 for t in thr):
            raise ValueError(f"thresholds must be in (0, 1), got {list(thr)}")

    @property
    def lowest(self) -> float:
        """The threshold to decode at before :meth:`keep` drops the rest."""
        return min(self.thresholds)

    def squared_edges(self) -> np.ndarray:
        """(B - 1,) float64: the edges squared (bands are compared on x^2 + y^2)."""
        edges = np.asarray(self.edges_m, np.float64)
        return edges * edges

    def per_point(self, points: np.ndarray) -> np.ndarray:
        """points (M, >=3) [x, y, z, ...] metres -> (M,) float32 the threshold of each one's band:
        the number of squared edges <= x^2 + y^2, in float64 from the float32 coordinates (the
        decode kernels' rule, ``decode._passes``)."""
        x, y = points[:, 0].astype(np.float64), points[:, 1].astype(np.float64)
        band = np.searchsorted(self.squared_edges(), x * x + y * y, side="right")  # (M,) 0..len(edges)
        return np.asarray(self.thresholds, np.float32)[band]

    def keep(self, points: np.ndarray, confidence: np.ndarray) -> np.ndarray:
        """points (M, >=3), confidence (M,) occupancy -> (M,) bool: confidence > its band's
        threshold (the decoder's own comparison, ``occupancy > threshold`` in float32)."""
        return np.asarray(confidence, np.float32) > self.per_point(points)

    def to_json(self) -> dict[str, list[float]]:
        return {"edges_m": list(self.edges_m), "thresholds": list(self.thresholds)}


def range_thresholds_from(block: Any, where: str | Path) -> RangeThresholds:
    """The manifest's ``range_thresholds`` block -> :class:`RangeThresholds` (one-line
    :class:`MsdnetError` naming ``where`` when it is malformed)."""
    if not isinstance(block, dict) or set(block) != {"edges_m", "thresholds"}:
        raise MsdnetError(where, "range_thresholds needs exactly 'edges_m' and 'thresholds'")
    values = []
    for key in ("edges_m", "thresholds"):
        seq = block[key]
        if not isinstance(seq, list) or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) for v in seq
        ):
            raise MsdnetError(where, f"range_thresholds {key} must be a list of numbers")
        values.append(tuple(float(v) for v in seq))
    try:
        return RangeThresholds(values[0], values[1])
    except ValueError as err:
        raise MsdnetError(where, f"range_thresholds: {err}") from None
