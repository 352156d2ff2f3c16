"""The R2LDM authors' formulas, as their public evaluation script (``eval_metric_2025.py``,
``metrics/bev.py``) computes them, so that numbers can be set beside the R2LDM / MSDNet tables.

Distances here are SQUARED. Per frame both clouds go through the script's preprocessing (0.125 m
voxel centroids inside [-16, 16] x [-16, 16] x [-0.5, 4.5] m), then squared CD as a sum, squared
Hausdorff and F@0.05 m; frames where either side is empty are skipped, as the script skips them.
Set level: JSD and MMD over the per-frame BEV histograms of the valid frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from msdnet.runtime.metrics.cloud import directed_distances

OFFICIAL_RANGE = (-16.0, -16.0, -0.5, 16.0, 16.0, 4.5)  # m: crop [x0, y0, z0, x1, y1, z1), half-open
OFFICIAL_VOXEL = 0.125  # m: voxel-centroid preprocessing of both clouds
OFFICIAL_FSCORE = 0.05  # m: F-score threshold (compared as d^2 <= t^2)
OFFICIAL_BEV = {"field": 160.0, "bins": 100, "min_depth": 3.0, "max_depth": 70.0}  # m, m, m
OFFICIAL_MMD_SIGMA = 0.5  # RBF width on the normalised (flattened) BEV histograms


def official_centroids(
    points: np.ndarray, point_range: tuple[float, ...] = OFFICIAL_RANGE, voxel: float = OFFICIAL_VOXEL
) -> np.ndarray:
    """(N, >=3) -> (M, 3) float32: the points inside ``point_range`` (lo <= p < hi per axis), one
    centroid per occupied ``voxel``-metre cell (the script's preprocessing, in float32 like it)."""
    xyz = np.asarray(points, dtype=np.float32)[:, :3]
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    lo = np.asarray(point_range[:3], np.float32)
    hi = np.asarray(point_range[3:], np.float32)
    xyz = xyz[((xyz >= lo) & (xyz < hi)).all(axis=1)]
    if len(xyz) == 0:
        return np.empty((0, 3), np.float32)
    cells = np.floor((xyz - lo) / np.float32(voxel)).astype(np.int64)
    _, inverse = np.unique(cells, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((inverse.max() + 1, 3), np.float64)
    np.add.at(sums, inverse, xyz)
    counts = np.bincount(inverse).astype(np.float64)
    return (sums / counts[:, None]).astype(np.float32)


def official_scores(pred: np.ndarray, gt: np.ndarray, preprocess: bool = True) -> dict[str, float]:
    """The script's per-frame geometry, after :func:`official_centroids` of both clouds.

    With ``d2(p, G) = min_g ||p - g||^2`` (m^2): ``chamfer_squared_l2 = mean_P d2 + mean_G d2`` (a SUM
    of the two means, not their average), ``hausdorff_squared_l2 = max(max_P d2, max_G d2)`` (the
    classic Hausdorff distance, squared), ``precision = share of P with d2 <= 0.05^2``, ``recall``
    likewise for G, ``fscore = 2 P R / (P + R + 1e-8)``; ``generated_points`` / ``ground_truth_points``
    after preprocessing. ``valid`` is 0.0 (and the distances nan) when either cloud is empty: the
    script skips such frames, so set means leave them out.
    """
    p = official_centroids(pred) if preprocess else np.asarray(pred, np.float32)[:, :3]
    g = official_centroids(gt) if preprocess else np.asarray(gt, np.float32)[:, :3]
    out = {"generated_points": float(len(p)), "ground_truth_points": float(len(g))}
    if len(p) == 0 or len(g) == 0:
        nan = float("nan")
        keys = ("chamfer_squared_l2", "hausdorff_squared_l2", "fscore", "precision", "recall")
        return {**dict.fromkeys(keys, nan), **out, "valid": 0.0}
    d_pg = directed_distances(p, g) ** 2
    d_gp = directed_distances(g, p) ** 2
    t2 = OFFICIAL_FSCORE**2
    precision, recall = float(np.mean(d_pg <= t2)), float(np.mean(d_gp <= t2))
    return {
        "chamfer_squared_l2": float(d_pg.mean() + d_gp.mean()),
        "hausdorff_squared_l2": float(max(d_pg.max(), d_gp.max())),
        "fscore": 2 * precision * recall / (precision + recall + 1e-8),
        "precision": precision,
        "recall": recall,
        **out,
        "valid": 1.0,
    }


def official_bev_histogram(points: np.ndarray) -> np.ndarray:
    """(N, >=3) -> (100, 100) float64 counts: x, y of the points with 3 < ||p||_2 < 70 m on a
    160 m square centred on the sensor (1.6 m cells), as the script's BEV histogram."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    depth = np.linalg.norm(xyz, axis=1)
    xy = xyz[(depth > OFFICIAL_BEV["min_depth"]) & (depth < OFFICIAL_BEV["max_depth"]), :2]
    b = OFFICIAL_BEV["field"] / 2
    h, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=int(OFFICIAL_BEV["bins"]), range=((-b, b), (-b, b)))
    return h


def official_set_scores(gt_hists: list[np.ndarray], gen_hists: list[np.ndarray]) -> dict[str, float]:
    """Set-level BEV scores over the frame pairs whose two histograms are non-empty.

    ``jsd``: scipy's Jensen-Shannon DISTANCE (natural log; the square root of the divergence)
    between the set-summed histograms, each normalised to sum 1. ``mmd``: with per-frame
    distributions ``p_i`` (real) and ``q_j`` (generated) and ``k(a, b) = exp(-||a - b||^2 / (2 *
    0.5^2))``, ``mean_ij k(p_i, p_j) + mean_ij k(q_i, q_j) - 2 mean_ij k(p_i, q_j)`` (diagonals
    included). nan with no pair.
    """
    from scipy.spatial.distance import cdist, jensenshannon

    keep = [(a, b) for a, b in zip(gt_hists, gen_hists, strict=True) if a.sum() > 0 and b.sum() > 0]
    if not keep:
        return {"jsd": float("nan"), "mmd": float("nan"), "valid_pairs": 0.0}
    real = np.stack([a.ravel() for a, _ in keep])  # (N, bins^2)
    gen = np.stack([b.ravel() for _, b in keep])
    jsd_value = float(jensenshannon(real.sum(0) / real.sum(), gen.sum(0) / gen.sum()))
    p = real / real.sum(1, keepdims=True)
    q = gen / gen.sum(1, keepdims=True)
    gamma = 1.0 / (2 * OFFICIAL_MMD_SIGMA**2)

    def k(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.exp(-gamma * cdist(a, b, "sqeuclidean")).mean())

    return {"jsd": jsd_value, "mmd": k(p, p) + k(q, q) - 2 * k(p, q), "valid_pairs": float(len(keep))}


# per-frame keys averaged over valid frames, as the script's "mean" block
FRAME_KEYS = (
    "chamfer_squared_l2",
    "hausdorff_squared_l2",
    "fscore",
    "precision",
    "recall",
    "generated_points",
    "ground_truth_points",
)


@dataclass
class OfficialFrames:
    """One method's official per-frame scores and the BEV histograms of its valid frames."""

    rows: list[dict[str, float]] = field(default_factory=list)  # one per frame (``valid`` 0 or 1)
    gt_hists: list[np.ndarray] = field(default_factory=list)  # (100, 100) per valid frame
    gen_hists: list[np.ndarray] = field(default_factory=list)

    def add(self, pred: np.ndarray, ref: np.ndarray) -> None:
        """Score one frame: pred, ref (M, 3) float32 metres."""
        p, g = official_centroids(pred), official_centroids(ref)
        row = official_scores(p, g, preprocess=False)
        self.rows.append(row)
        if row["valid"]:
            self.gt_hists.append(official_bev_histogram(g))
            self.gen_hists.append(official_bev_histogram(p))

    def summary(self) -> dict[str, float]:
        """Means of ``FRAME_KEYS`` over valid frames, ``jsd`` / ``mmd`` / ``valid_pairs``, and
        ``pairs_evaluated`` / ``pairs_skipped_empty``."""
        valid = [r for r in self.rows if r["valid"]]
        nan = float("nan")
        out = {k: float(np.mean([r[k] for r in valid])) if valid else nan for k in FRAME_KEYS}
        out.update(official_set_scores(self.gt_hists, self.gen_hists))
        out["pairs_evaluated"] = float(len(valid))
        out["pairs_skipped_empty"] = float(len(self.rows) - len(valid))
        return out
