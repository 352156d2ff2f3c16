"""Occupancy threshold chosen on TRAINING frames (never validation): ``msdnet-export --calibrate``.

A model trained with a weighted occupancy loss (``--occ-pos-weight w``) over-states every
probability (odds times ``w``), so its right decoding threshold is not 0.5. For each candidate
threshold this decodes the model's full-scale prediction of a few evenly spaced training frames
exactly as the runtime does (``runtime.decode.decode_occupancy``), crops it like the evaluation
does (``benchmarks.quality.crop_to_grid``) and scores it against the frame's LiDAR reference with
the Chamfer distance (``benchmarks.metrics``). The threshold with the lowest mean Chamfer
distance wins; the whole table is returned so the choice can be reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from msdnet.runtime.decode import decode_occupancy
from msdnet.runtime.errors import MsdnetError
from msdnet.training.batch import collate
from msdnet.training.config import ModelConfig
from msdnet.training.data import make_splits

CANDIDATES = tuple(round(t, 2) for t in np.arange(0.05, 0.96, 0.05))  # thresholds tried


@dataclass(frozen=True)
class ThresholdRow:
    """Mean figures of one candidate threshold over the calibration frames."""

    threshold: float  # occupancy threshold tried
    cd: float  # mean Chamfer distance to the LiDAR reference, metres (empty outputs excluded)
    fscore: float  # mean F-score at 0.5 m
    points: float  # mean decoded points per frame (cropped like the reference)
    empty: int  # frames that decoded no point


def pick_frames(n_train: int, frames: int) -> list[int]:
    """``frames`` indices spread evenly over ``range(n_train)``."""
    if n_train == 0:
        raise MsdnetError(None, "the training split is empty: nothing to calibrate on")
    return sorted({int(i) for i in np.linspace(0, n_train - 1, min(frames, n_train))})


def calibrate_threshold(
    model: torch.nn.Module,
    cfg: ModelConfig,
    dataset: str,
    root: str,
    frames: int = 24,
    val_fraction: float = 0.2,
    seed: int = 0,
) -> tuple[float, list[ThresholdRow]]:
    """(best threshold, table) on ``frames`` training frames of ``root``; the model is a student
    or R2LDM whose ``predict(radar)`` gives full-scale (occ (B, D, H, W), off (B, 3, D, H, W))."""
    from msdnet.benchmarks.metrics import chamfer_distance, fscore
    from msdnet.benchmarks.quality import crop_to_grid

    train, _ = make_splits(dataset, root, cfg, val_fraction=val_fraction)
    picks = pick_frames(len(train), frames)
    torch.manual_seed(seed)
    stats: dict[float, list[tuple[float, float, int]]] = {t: [] for t in CANDIDATES}
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
                    stats[t].append((float("nan"), 0.0, 0))
                else:
                    stats[t].append((chamfer_distance(pred, ref), fscore(pred, ref, 0.5), len(pred)))
    rows = []
    for t, vals in stats.items():
        cds = [v[0] for v in vals if np.isfinite(v[0])]
        rows.append(
            ThresholdRow(
                threshold=t,
                cd=float(np.mean(cds)) if cds else float("inf"),
                fscore=float(np.mean([v[1] for v in vals])),
                points=float(np.mean([v[2] for v in vals])),
                empty=len(vals) - len(cds),
            )
        )
    usable = [r for r in rows if r.empty == 0] or rows
    best = min(usable, key=lambda r: r.cd)
    if not np.isfinite(best.cd):
        raise MsdnetError(root, "no threshold decodes any point on the calibration frames")
    return best.threshold, rows
