"""Occupancy threshold chosen on held-out TRAINING-range frames: ``msdnet-export --calibrate``.

The frames are the checkpoint's selection slice (``msdnet-train --holdout``: the last frames of
the training range, which the weights were not fitted on and which are not the validation split);
a run without a holdout calibrates on its training frames (over-fitted ones: avoid).

A model trained with a weighted occupancy loss (``--occ-pos-weight w``) over-states every
probability (odds times ``w``), so its right decoding threshold is not 0.5. For each candidate
threshold this decodes the model's full-scale prediction of a few evenly spaced training frames
exactly as the runtime does (``runtime.engine.decode.decode_occupancy``), crops it like the evaluation
does (``benchmarks.quality.suite.crop_to_grid``) and scores it against the frame's LiDAR reference with
the paper's five headline metrics (``runtime.metrics.cloud.score_frame``: Chamfer distance, modified
Hausdorff distance, F-score at 0.5 m, BEV JSD and MMD). Each metric ranks the thresholds by its
mean over the frames; the threshold with the best mean rank wins (ties: lower Chamfer distance).
Ranking, not one metric alone: the Chamfer distance keeps falling as points are sprayed around,
while MMD and MHD punish it. The whole table is returned so the choice can be reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from msdnet.runtime.engine.decode import decode_occupancy
from msdnet.runtime.errors import MsdnetError
from msdnet.training.config import ModelConfig
from msdnet.training.data.batch import collate
from msdnet.training.data.datasets import make_splits

CANDIDATES = tuple(round(t, 2) for t in np.arange(0.05, 0.96, 0.05))  # thresholds tried


@dataclass(frozen=True)
class ThresholdRow:
    """Mean figures of one candidate threshold over the calibration frames."""

    threshold: float  # occupancy threshold tried
    cd: float  # mean Chamfer distance to the LiDAR reference, metres (empty outputs excluded)
    mhd: float  # mean modified Hausdorff distance, metres (empty outputs excluded)
    fscore: float  # mean F-score at 0.5 m (empty outputs count 0)
    jsd: float  # mean BEV Jensen-Shannon divergence, bits (empty outputs excluded)
    mmd: float  # mean BEV squared MMD (empty outputs excluded)
    points: float  # mean decoded points per frame (cropped like the reference)
    empty: int  # frames that decoded no point
    rank: float  # mean rank over (cd, mhd, fscore, jsd, mmd); 1 = best on every metric


def pick_frames(n_train: int, frames: int) -> list[int]:
    """``frames`` indices spread evenly over ``range(n_train)``."""
    if n_train == 0:
        raise MsdnetError(None, "the training split is empty: nothing to calibrate on")
    return sorted({int(i) for i in np.linspace(0, n_train - 1, min(frames, n_train))})


RANKED = {"cd": True, "mhd": True, "fscore": False, "jsd": True, "mmd": True}  # metric -> lower is better


def calibrate_threshold(
    model: torch.nn.Module,
    cfg: ModelConfig,
    dataset: str,
    root: str,
    frames: int = 24,
    val_fraction: float = 0.2,
    seed: int = 0,
    holdout: float = 0.0,
) -> tuple[float, list[ThresholdRow]]:
    """(best threshold, table) on ``frames`` frames of ``root``: of the selection slice ``holdout``
    of the training range when > 0 (``make_splits``), else of the training range. The model is a
    student or R2LDM whose ``predict(radar)`` gives full-scale (occ (B, D, H, W), off (B, 3, D, H, W))."""
    from msdnet.runtime.metrics.cloud import score_frame
    from msdnet.runtime.metrics.crop import crop_to_grid, xy_range

    fit, select = make_splits(dataset, root, cfg, val_fraction=val_fraction, holdout=holdout)
    train = select if holdout > 0 else fit
    picks = pick_frames(len(train), frames)
    torch.manual_seed(seed)
    per: dict[float, list[dict[str, float]]] = {t: [] for t in CANDIDATES}
    model.eval()
    with torch.no_grad():
        for i in picks:
            radar, lidar = train[i]
            batch = collate([(radar, lidar)], cfg)
            occ, off = model.predict(batch.radar)  # noise from the seeded global generator
            occ_np, off_np = occ[0].numpy(), off[0].numpy()  # (D, H, W), (3, D, H, W)
            ref = np.ascontiguousarray(lidar[:, :3], dtype=np.float32)
            for t in CANDIDATES:
                pts, _ = decode_occupancy(occ_np, off_np, cfg.grid, t)
                pred = crop_to_grid(pts, cfg.grid)
                if len(pred) == 0 or len(ref) == 0:
                    per[t].append({"fscore": 0.0, "points": 0.0})
                    continue
                sc = score_frame(pred, ref, xy_range(cfg.grid))
                per[t].append(
                    {"cd": sc.cd, "mhd": sc.mhd, "fscore": sc.fscore[0.5], "jsd": sc.jsd, "mmd": sc.mmd}
                    | {"points": float(len(pred))}
                )
    means = {
        t: {k: _mean([v[k] for v in vals if k in v]) for k in [*RANKED, "points"]} for t, vals in per.items()
    }
    ranks = {t: 0.0 for t in CANDIDATES}
    for k, lower in RANKED.items():
        order = sorted(CANDIDATES, key=lambda t: means[t][k] if lower else -means[t][k])
        for r, t in enumerate(order, start=1):
            ranks[t] += r / len(RANKED)
    rows = [
        ThresholdRow(
            t,
            **{k: means[t][k] for k in RANKED},
            points=means[t]["points"],
            empty=sum("cd" not in v for v in per[t]),
            rank=ranks[t],
        )
        for t in CANDIDATES
    ]
    usable = [r for r in rows if r.empty == 0] or [r for r in rows if np.isfinite(r.cd)]
    if not usable:
        raise MsdnetError(root, "no threshold decodes any point on the calibration frames")
    best = min(usable, key=lambda r: (r.rank, r.cd))
    return best.threshold, rows


def _mean(values: list[float]) -> float:
    """Mean, or +inf for no values (a threshold that decodes nothing ranks last)."""
    return float(np.mean(values)) if values else float("inf")
