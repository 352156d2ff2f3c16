"""Useful-FLOP efficiency per stage: how far each stage is from the machine's limit.

For one frame (the timing input and what the pipeline decodes from it), a stage's useful FLOPs
are the FLOPs its graph needs on occupied voxels only:

- encoder: a rulebook-fed matmul counts its rulebook's real entries only (a tap with no input
  voxel is no work); the per-voxel VFE counts whole; a convolution over the BEV map counts the
  cells under an input voxel;
- RGFD + adapter, DDIM loop (every call), head: a convolution counts the output positions under an
  occupied voxel, at its own output resolution (2D: BEV cells, 3D: voxels); an occupied voxel is a
  full-scale voxel that holds an input radar point or a decoded point. The head is counted on the
  dense reference graph whichever head the pipeline ran;
- anything else (the time embedding, the adapter's pooled MLP) counts whole.

efficiency = useful FLOPs / (the stage's median time x the machine's sgemm rate): 1.0 is a stage
that does only the occupied work, at the rate of a large float32 matmul.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from msdnet.benchmarks.flops import NodeFlops, node_flops
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.voxelize import voxelize
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.spec.grid import GridConfig

STAGE_GRAPHS = {  # latency stage -> the graph whose FLOPs it needs (the loop: the step graph, per call)
    "encoder": onnx_spec.ENCODER.file,
    "rgfd_adapter": onnx_spec.RGFD_ADAPTER.file,
    "ddim_loop": onnx_spec.DENOISER_STEP.file,
    "recon_head": onnx_spec.RECON_HEAD.file,
}


def voxel_mask(grid: GridConfig, points: np.ndarray) -> np.ndarray:
    """(D, H, W) bool: the full-scale voxels holding any of ``points`` (M, >=3) [x, y, z] metres."""
    d, h, w = grid.shape_zyx
    mask = np.zeros((d, h, w), bool)
    if len(points) == 0:
        return mask
    lo, size = np.asarray(grid.point_range[:3]), np.asarray(grid.voxel_size)
    idx = np.floor((np.asarray(points[:, :3], np.float64) - lo) / size).astype(np.int64)  # (M, 3) x y z
    keep = np.all((idx >= 0) & (idx < np.array([w, h, d])), axis=1)
    mask[idx[keep, 2], idx[keep, 1], idx[keep, 0]] = True
    return mask


def occupied_share(mask: np.ndarray, spatial: tuple[int, ...]) -> float:
    """Share of the positions of a (d, h, w) volume or an (h, w) map that lie under an occupied
    voxel of ``mask`` (D, H, W): position p of n along an axis of N covers voxels p * N / n on."""
    z, y, x = np.nonzero(mask)
    dims = mask.shape
    if len(spatial) == 2:
        z, dims = np.zeros_like(z), (1, *dims[1:])
        spatial = (1, *spatial)
    if len(spatial) != 3 or min(spatial) < 1:
        return 1.0
    cells = {
        (int(a), int(b), int(c))
        for a, b, c in zip(
            z * spatial[0] // dims[0], y * spatial[1] // dims[1], x * spatial[2] // dims[2], strict=True
        )
    }
    return len(cells) / float(np.prod(spatial))


def useful(nodes: list[NodeFlops], share: Callable[[NodeFlops], float]) -> tuple[float, float]:
    """(FLOPs, useful FLOPs) of ``nodes``, each node's FLOPs times ``share(node)``."""
    return float(sum(n.flops for n in nodes)), float(sum(n.flops * share(n) for n in nodes))


def _conv_share(mask: np.ndarray) -> Callable[[NodeFlops], float]:
    def share(node: NodeFlops) -> float:
        if node.op in ("Conv", "ConvTranspose", "DeformConv") and len(node.out_shape) in (4, 5):
            return occupied_share(mask, node.out_shape[2:])
        return 1.0

    return share


def stage_flops(pipe: Pipeline, points: Any, threshold: float, seed: int = 0) -> dict[str, dict[str, float]]:
    """Per stage of ``STAGE_GRAPHS`` the pipeline's graphs have: {"gflop": the graph's FLOPs at
    this frame, "gflop_useful": on occupied voxels only (module docstring), "useful_share"}; the
    loop's are a call's times the calls of a frame."""
    pts = pipe.select_columns(points)
    res = pipe(points, threshold=threshold, seed=seed)
    grid = pipe.artifact.grid
    vox = voxelize(pts, grid, pipe.artifact.inputs.max_voxels)
    radar = np.zeros(grid.shape_zyx, bool)  # (D, H, W): the input voxels
    radar[tuple(np.asarray(vox.coords, np.int64).T)] = True
    occupied = radar | voxel_mask(grid, res.points)
    feeds, _, _ = pipe.encoder_feeds(pts)
    root = pipe.artifact.root
    out: dict[str, dict[str, float]] = {}
    if feeds:
        rows = {name: arr.shape[0] for name, arr in feeds.items()}

        def enc_share(node: NodeFlops) -> float:
            if node.rules is not None:
                rules = feeds[node.rules]
                level = int(node.rules.rsplit("_", 1)[1])
                n_in = rows[f"subm_rules_{level - 1}"] if node.rules.startswith("down") else len(rules)
                return float(np.mean(rules < n_in)) if rules.size else 0.0
            return _conv_share(radar)(node)

        shapes = {k: v.shape for k, v in feeds.items()}
        out["encoder"] = _row(*useful(node_flops(root / STAGE_GRAPHS["encoder"], shapes), enc_share))
    bev = pipe.bev_shape
    share = _conv_share(occupied)
    if onnx_spec.RGFD_ADAPTER.file in pipe.sessions:
        nodes = node_flops(root / onnx_spec.RGFD_ADAPTER.file, {"bev_features": bev, "noise": bev})
        out["rgfd_adapter"] = _row(*useful(nodes, share))
    step = onnx_spec.DENOISER_STEP if pipe.kind == "student" else onnx_spec.R2LDM_STEP
    scalars = {k: (1,) for k in ("t", "abar_t", "abar_prev")}
    nodes = node_flops(root / step.file, {"x_t": bev, "cond": bev, **scalars})
    calls = int(pipe.coefficients().shape[0])
    total, used = useful(nodes, share)
    out["ddim_loop"] = _row(total * calls, used * calls)
    out["recon_head"] = _row(*useful(node_flops(root / onnx_spec.RECON_HEAD.file, {"features": bev}), share))
    return out


def _row(total: float, used: float) -> dict[str, float]:
    return {"gflop": total / 1e9, "gflop_useful": used / 1e9, "useful_share": used / total if total else 0.0}


def efficiency(
    flops: dict[str, dict[str, float]], stages_ms: dict[str, dict[str, float]], sgemm_gflops: float
) -> dict[str, dict[str, float]]:
    """``flops`` (:func:`stage_flops`) with each stage's median ms, its useful FLOP rate and its
    efficiency (module docstring), and a "graphs" row over all of them."""
    out: dict[str, dict[str, float]] = {}
    for stage, row in flops.items():
        ms = float(stages_ms[stage]["median"])
        rate = row["gflop_useful"] / (ms / 1e3) if ms > 0 else float("nan")
        out[stage] = row | {"ms": ms, "useful_gflops_rate": rate, "efficiency": rate / sgemm_gflops}
    if out:
        ms = sum(r["ms"] for r in out.values())
        total, used = sum(r["gflop"] for r in out.values()), sum(r["gflop_useful"] for r in out.values())
        rate = used / (ms / 1e3) if ms > 0 else float("nan")
        out["graphs"] = _row(total * 1e9, used * 1e9) | {
            "ms": ms,
            "useful_gflops_rate": rate,
            "efficiency": rate / sgemm_gflops,
        }
    return out
