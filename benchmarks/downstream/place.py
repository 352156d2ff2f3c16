"""ScanContext place recognition (Kim and Kim, IROS 2018) and Recall@K.

A descriptor is a polar BEV grid (rings x sectors) holding the highest point per bin; retrieval
takes the nearest ring keys, then the column-shift-invariant ScanContext distance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class ScanContextConfig:
    """Descriptor and retrieval settings."""

    rings: int = 20  # radial bins
    sectors: int = 60  # azimuth bins over the full circle
    max_range: float = 50.0  # m: outer radius of the descriptor
    height_offset: float = 2.0  # m added to z so that bins hold positive heights
    candidates: int = 10  # ring-key neighbours re-ranked by the full distance


def scan_context(points: np.ndarray, cfg: ScanContextConfig) -> np.ndarray:
    """(rings, sectors) float64: max ``z + height_offset`` per polar bin (0 where empty).

    points: (N, >=3) [x, y, z] metres in the sensor frame.
    """
    desc = np.zeros((cfg.rings, cfg.sectors))
    if len(points) == 0:
        return desc
    x, y, z = points[:, 0], points[:, 1], points[:, 2] + cfg.height_offset
    r = np.hypot(x, y)
    keep = (r < cfg.max_range) & (z > 0)
    ring = np.minimum((r[keep] / cfg.max_range * cfg.rings).astype(int), cfg.rings - 1)
    theta = np.mod(np.arctan2(y[keep], x[keep]), 2 * np.pi)
    sector = np.minimum((theta / (2 * np.pi) * cfg.sectors).astype(int), cfg.sectors - 1)
    np.maximum.at(desc, (ring, sector), z[keep])
    return desc


def ring_key(desc: np.ndarray) -> np.ndarray:
    """(rings,) rotation-invariant key: share of occupied sectors per ring."""
    return (desc > 0).mean(axis=1)


def sc_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Min over column shifts of the mean cosine distance between matching non-empty columns."""
    best = np.inf
    na = np.linalg.norm(a, axis=0)
    for shift in range(a.shape[1]):
        bs = np.roll(b, shift, axis=1)
        nb = np.linalg.norm(bs, axis=0)
        valid = (na > 0) & (nb > 0)
        if not valid.any():
            continue
        cos = np.sum(a[:, valid] * bs[:, valid], axis=0) / (na[valid] * nb[valid])
        best = min(best, float(np.mean(1.0 - cos)))
    return best if np.isfinite(best) else 1.0


@dataclass(frozen=True)
class RecallResult:
    """Place-recognition recall over revisit queries."""

    recall: dict[int, float]  # K -> share of queries with a true match in the top K
    queries: int  # frames that had at least one true match in the database


def recall_at_k(
    clouds: list[np.ndarray],
    positions: np.ndarray,
    ks: tuple[int, ...] = (1, 3, 5),
    revisit_radius: float = 5.0,
    exclude_recent: int = 50,
    cfg: ScanContextConfig | None = None,
) -> RecallResult:
    """Recall@K of ScanContext over one sequence.

    clouds: per frame (N_i, >=3) sensor-frame points; positions: (F, 2 or 3) true positions in
    metres. Frame ``q`` queries the database of frames ``< q - exclude_recent``; a retrieved frame
    is correct when it lies within ``revisit_radius`` metres of ``q``. Queries without any correct
    frame in their database are skipped.
    """
    cfg = cfg or ScanContextConfig()
    descs = [scan_context(c, cfg) for c in clouds]
    keys = np.stack([ring_key(d) for d in descs])
    pos = np.asarray(positions, dtype=np.float64)
    hits = {k: 0 for k in ks}
    queries = 0
    for q in range(len(clouds)):
        db = q - exclude_recent
        if db <= 0:
            continue
        true = np.linalg.norm(pos[:db] - pos[q], axis=1) < revisit_radius
        if not true.any():
            continue
        queries += 1
        n_cand = min(max(cfg.candidates, max(ks)), db)
        _, idx = cKDTree(keys[:db]).query(keys[q], k=n_cand)
        idx = np.atleast_1d(idx)
        ranked = sorted(idx, key=lambda i: sc_distance(descs[q], descs[i]))
        for k in ks:
            hits[k] += bool(true[ranked[:k]].any())
    recall = {k: hits[k] / queries if queries else float("nan") for k in ks}
    return RecallResult(recall=recall, queries=queries)
