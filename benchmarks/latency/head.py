"""The coarse-to-fine head against the dense reference head, in one run on one input.

The gate: a given model's manifest ``gate`` (calibrated by ``export.gate``); random weights have
no calibrated gate, so the timing input sets one the way it sets the threshold: the quantile of the
half-scale occupancy keeping ``RANDOM_VOXEL_SHARE`` of the half-scale voxels (the shipped models'
calibrated gates keep 2.2-4.8 %), or at least a quarter of the target point count (8 children
each), so that the threshold chosen after it still leaves the target number of points. Sparse
and dense calls alternate, so both see the same load.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msdnet.benchmarks.latency.timing import Scan, summary
from msdnet.export.gate import keep_all_gate
from msdnet.runtime.engine.pipeline import Pipeline

RANDOM_VOXEL_SHARE = 0.05  # random weights: share of the half-scale voxels the gate keeps
CLOSE_M = 1e-4  # m: keep-every-point points "equal within rounding" (gated head: other sum order)
AT_THRESHOLD = 1e-5  # occupancy this close to the threshold may fall on either side in another sum order


def apart_at_threshold(a: Any, b: Any, threshold: float) -> int | None:
    """Two decodings ``a``, ``b`` (``points`` (M, 3), ``confidence`` (M,)) of the same input: how many
    points only one of them decodes, if each of those lies within ``AT_THRESHOLD`` of ``threshold``
    (rounding may put it on either side) and every other point has a twin within ``CLOSE_M``; else
    None."""
    from scipy.spatial import cKDTree

    pa, pb = np.asarray(a.points, np.float64), np.asarray(b.points, np.float64)
    alone = 0
    for p, q, conf in ((pa, pb, a.confidence), (pb, pa, b.confidence)):
        if not len(p):
            continue
        lone = np.ones(len(p), bool) if not len(q) else cKDTree(q).query(p)[0] > CLOSE_M  # (M,)
        if np.any(np.abs(np.asarray(conf, np.float64)[lone] - threshold) > AT_THRESHOLD):
            return None
        alone += int(lone.sum())
    return alone


def choose_gate(pipe: Pipeline, points: Scan, weights: str, target: int, seed: int = 0) -> str:
    """Set ``pipe.gate`` for the run (see the module docstring); -> a note saying how."""
    if pipe.artifact.gate is not None and weights != "random":
        if pipe.auto is not None and pipe.auto.dense_head:
            pipe.gate = None
            return (
                f"dense head: provider auto found it faster here than the coarse-to-fine head at the "
                f"manifest gate {pipe.artifact.gate:.4g}"
            )
        pipe.gate = pipe.artifact.gate
        return f"manifest gate {pipe.gate:.4g}"
    if not pipe.sessions.get("recon_head_sparse.onnx"):
        pipe.gate = None
        return "no recon_head_sparse.onnx: dense head"
    pipe.gate = 0.0
    pipe(points, seed=seed)
    occ = np.sort(pipe.sparse_head_outputs()["gate_occupancy"])[::-1]  # (N,) descending
    keep = min(len(occ), max(int(RANDOM_VOXEL_SHARE * len(occ)), -(-target // 4)))
    pipe.gate = float(np.nextafter(occ[keep], np.float32(0))) if keep < len(occ) else 0.0
    return (
        f"random weights: gate {pipe.gate:.4g}, keeping {keep} of {len(occ)} half-scale voxels "
        f"(>= {RANDOM_VOXEL_SHARE:.0%}, >= a quarter of the target points)"
    )


def coarse_to_fine_gate(pipe: Pipeline) -> float | None:
    """The gate the coarse-to-fine head runs with: ``pipe.gate``, else the manifest's (``--provider
    auto`` may run the dense head); None when there is none."""
    return pipe.gate if pipe.gate is not None else pipe.artifact.gate


def head_comparison(
    pipe: Pipeline, points: Scan, threshold: float, repeats: int, seed: int = 0, gate: float | None = None
) -> dict[str, Any]:
    """Head stage of the coarse-to-fine head at ``gate`` (default ``pipe.gate``) vs the dense head,
    alternating calls; decoded points of each, and a check: with the keep-every-point gate of this
    input, the sparse head decodes exactly the dense head's points. ``pipe.gate`` is left as it was."""
    runs_with = pipe.gate
    gate = runs_with if gate is None else gate
    if gate is None:
        return {"note": "no gate: the pipeline runs the dense head"}
    sparse_s, dense_s = [], []
    try:
        for _ in range(repeats):
            pipe.gate = gate
            sparse = pipe(points, threshold=threshold, seed=seed)
            sparse_s.append(sparse.timings["head"])
            pipe.gate = None
            dense = pipe(points, threshold=threshold, seed=seed)
            dense_s.append(dense.timings["head"])
        pipe.gate = 0.0
        pipe(points, threshold=threshold, seed=seed)
        out = pipe.sparse_head_outputs()
        kag = keep_all_gate(out["occupancy"], out["gate_occupancy"], threshold)
        pipe.gate = kag
        keep_all = pipe(points, threshold=threshold, seed=seed)
    finally:
        pipe.gate = runs_with
    s, d = summary(sparse_s), summary(dense_s)
    return {
        "gate": gate,
        "sparse": s,
        "dense": d,
        "head_over_dense_head": s["median"] / d["median"],
        "head_voxels": sparse.stats["head_voxels"],
        "half_voxels": dense.stats["head_voxels"],
        "points_sparse": len(sparse.points),
        "points_dense": len(dense.points),
        "points_lost_share": 1.0 - len(sparse.points) / max(1, len(dense.points)),
        "keep_all_gate": kag,
        "keep_all_equal": bool(np.array_equal(keep_all.points, dense.points)),
        # the gated head's 1/2 conv is a gather + matmul: the same sums in another order
        "keep_all_close": bool(
            keep_all.points.shape == dense.points.shape
            and np.allclose(keep_all.points, dense.points, rtol=0, atol=CLOSE_M)
        ),
        # else: equal but for the points at the threshold (random weights put it on a point's occupancy)
        "keep_all_apart_at_threshold": apart_at_threshold(keep_all, dense, threshold),
    }
