"""Point-cloud quality metrics, each defined once (MSDNet Sec. IV-C; R2LDM Sec. IV).

All inputs are ``(N, >=3) float`` arrays whose first three columns are ``[x, y, z]`` in metres in
the radar frame; nearest neighbours come from :class:`scipy.spatial.cKDTree`. A metric that needs
a point on both sides returns ``nan`` when either cloud is empty.

Notation: ``P`` the predicted cloud, ``G`` the reference (LiDAR) cloud,
``d(p, G) = min_{g in G} ||p - g||_2`` (metres), ``mean_P d = (1/|P|) sum_{p in P} d(p, G)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

FSCORE_THRESHOLDS = (0.05, 0.1, 0.2, 0.5)  # metres
BEV_BIN = 0.5  # metres per histogram cell for JSD / MMD
MMD_SIGMA = 1.0  # metres: Gaussian kernel width of the BEV MMD


def _xyz(points: np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=np.float64)[:, :3]


def directed_distances(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(|src|,) metres: ``d(s, dst)`` for every ``s`` in ``src`` (nearest neighbour in ``dst``)."""
    d, _ = cKDTree(_xyz(dst)).query(_xyz(src), k=1)
    return np.asarray(d, dtype=np.float64)


@dataclass(frozen=True)
class PairDistances:
    """Nearest-neighbour distances both ways between a prediction and a reference."""

    pred_to_ref: np.ndarray  # (|P|,) metres
    ref_to_pred: np.ndarray  # (|G|,) metres

    @classmethod
    def of(cls, pred: np.ndarray, ref: np.ndarray) -> PairDistances | None:
        if len(pred) == 0 or len(ref) == 0:
            return None
        return cls(directed_distances(pred, ref), directed_distances(ref, pred))


def chamfer_distance(pred: np.ndarray, ref: np.ndarray, squared: bool = False) -> float:
    """Chamfer distance, metres: ``CD = (mean_P d(p, G) + mean_G d(g, P)) / 2``.

    ``squared=True`` gives the squared variant (m^2): ``(mean_P d^2 + mean_G d^2) / 2`` — papers
    mix the two, so tables label which one they show.
    """
    pd = PairDistances.of(pred, ref)
    if pd is None:
        return float("nan")
    p = 2 if squared else 1
    return float(0.5 * (np.mean(pd.pred_to_ref**p) + np.mean(pd.ref_to_pred**p)))


def modified_hausdorff(pred: np.ndarray, ref: np.ndarray) -> float:
    """Modified Hausdorff distance (Dubuisson and Jain), metres: ``max(mean_P d, mean_G d)``."""
    pd = PairDistances.of(pred, ref)
    if pd is None:
        return float("nan")
    return float(max(np.mean(pd.pred_to_ref), np.mean(pd.ref_to_pred)))


def fscore(pred: np.ndarray, ref: np.ndarray, threshold: float) -> float:
    """F-score at ``threshold`` metres, unitless in [0, 1].

    precision = fraction of ``p`` with ``d(p, G) < t``; recall = fraction of ``g`` with
    ``d(g, P) < t``; ``F = 2 precision recall / (precision + recall)`` (0 when both are 0).
    """
    pd = PairDistances.of(pred, ref)
    if pd is None:
        return 0.0 if len(ref) else float("nan")
    precision = float(np.mean(pd.pred_to_ref < threshold))
    recall = float(np.mean(pd.ref_to_pred < threshold))
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


def bev_histogram(
    points: np.ndarray, xy_range: tuple[float, float, float, float], bin_size: float = BEV_BIN
) -> np.ndarray:
    """(nx, ny) float64 distribution: share of points per BEV cell of ``bin_size`` metres.

    ``xy_range = (x0, y0, x1, y1)``; points outside are ignored; an empty cloud gives all zeros.
    """
    x0, y0, x1, y1 = xy_range
    nx, ny = int(round((x1 - x0) / bin_size)), int(round((y1 - y0) / bin_size))
    xyz = _xyz(points)
    h, _, _ = np.histogram2d(xyz[:, 0], xyz[:, 1], bins=(nx, ny), range=((x0, x1), (y0, y1)))
    total = h.sum()
    return h / total if total > 0 else h


def jsd(p: np.ndarray, q: np.ndarray) -> float:
    """Jensen-Shannon divergence of two BEV histograms, bits, in [0, 1].

    ``JSD = KL(P || M) / 2 + KL(Q || M) / 2`` with ``M = (P + Q) / 2`` and base-2 logarithms.
    """
    p, q = p.ravel(), q.ravel()
    if p.sum() == 0 or q.sum() == 0:
        return float("nan")
    m = 0.5 * (p + q)

    def kl(a: np.ndarray) -> float:
        nz = a > 0
        return float(np.sum(a[nz] * np.log2(a[nz] / m[nz])))

    return 0.5 * kl(p) + 0.5 * kl(q)


def mmd(p: np.ndarray, q: np.ndarray, bin_size: float = BEV_BIN, sigma: float = MMD_SIGMA) -> float:
    """Squared maximum mean discrepancy of two BEV histograms, unitless.

    The histograms are distributions over cell centres; with a Gaussian kernel
    ``k(a, b) = exp(-||a - b||^2 / (2 sigma^2))`` (sigma in metres)
    ``MMD^2 = P'KP + Q'KQ - 2 P'KQ = (P - Q)' K (P - Q)``. K is separable in x and y, so it is
    applied as ``Kx (P - Q) Ky`` without forming the full matrix.
    """
    if p.sum() == 0 or q.sum() == 0:
        return float("nan")
    diff = p - q  # (nx, ny)

    def kernel(n: int) -> np.ndarray:
        c = np.arange(n) * bin_size
        return np.exp(-((c[:, None] - c[None, :]) ** 2) / (2 * sigma**2))

    smoothed = kernel(diff.shape[0]) @ diff @ kernel(diff.shape[1])
    return float(max(np.sum(diff * smoothed), 0.0))


@dataclass(frozen=True)
class FrameScores:
    """All metrics of one predicted cloud against its reference."""

    cd: float  # Chamfer distance, m
    cd_squared: float  # squared Chamfer distance, m^2
    mhd: float  # modified Hausdorff distance, m
    fscore: dict[float, float]  # threshold (m) -> F-score
    jsd: float  # BEV Jensen-Shannon divergence, bits
    mmd: float  # BEV squared MMD
    num_points: int  # points in the prediction


def score_frame(
    pred: np.ndarray, ref: np.ndarray, xy_range: tuple[float, float, float, float]
) -> FrameScores:
    """Every metric of ``pred`` against ``ref``; the BEV metrics over ``xy_range`` (x0, y0, x1, y1)."""
    hp, hr = bev_histogram(pred, xy_range), bev_histogram(ref, xy_range)
    return FrameScores(
        cd=chamfer_distance(pred, ref),
        cd_squared=chamfer_distance(pred, ref, squared=True),
        mhd=modified_hausdorff(pred, ref),
        fscore={t: fscore(pred, ref, t) for t in FSCORE_THRESHOLDS},
        jsd=jsd(hp, hr),
        mmd=mmd(hp, hr),
        num_points=int(len(pred)),
    )


# ---------------------------------------------------------------- the R2LDM authors' formulas
# As their public evaluation script (eval_metric_2025.py, metrics/bev.py) computes them, so that
# numbers can be set beside the R2LDM / MSDNet tables' formulas. Distances there are SQUARED.

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
