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


def scene_scores(
    pred: np.ndarray, ref: np.ndarray, xy_range: tuple[float, float, float, float]
) -> dict[str, float]:
    """The scene metrics a decoding choice is judged on, from one nearest-neighbour pass:
    {"cd", "mhd", "fscore@0.2", "fscore@0.5", "jsd"}, each equal to its function above (``score_frame``
    computes them one by one, with MMD and the squared CD)."""
    hp, hr = bev_histogram(pred, xy_range), bev_histogram(ref, xy_range)
    pd = PairDistances.of(pred, ref)
    if pd is None:
        nan = float("nan")
        empty_f = 0.0 if len(ref) else nan
        return {"cd": nan, "mhd": nan, "fscore@0.2": empty_f, "fscore@0.5": empty_f, "jsd": jsd(hp, hr)}
    a, b = float(np.mean(pd.pred_to_ref)), float(np.mean(pd.ref_to_pred))
    out = {"cd": float(0.5 * (a + b)), "mhd": float(max(a, b))}
    for t in (0.2, 0.5):
        precision = float(np.mean(pd.pred_to_ref < t))
        recall = float(np.mean(pd.ref_to_pred < t))
        both = precision + recall
        out[f"fscore@{t}"] = 0.0 if both == 0 else 2 * precision * recall / both
    return out | {"jsd": jsd(hp, hr)}
