"""Torch vs onnxruntime on the same inputs: per graph and end to end (``msdnet-export --verify``).

Per graph, the torch module and its ONNX graph (run by the artifact's own sessions) get the same
inputs: the encoder a voxelized frame, the other graphs the torch outputs of the graph before
(the step graph at its first, middle and last DDIM row). Reported per graph, worst over frames:

- ``max_abs`` = max |onnx - torch|;
- ``max_rel`` = max |onnx - torch| / max |torch| (relative to the output's scale, so values near
  zero do not blow it up);
- ``cosine`` = <onnx, torch> / (|onnx| |torch|) over the flattened output.

End to end, the runtime :class:`Pipeline` and the torch model's own ``predict`` (same noise, same
DDIM rows, the same decoder) densify each frame; a point "differs" when its voxel is
occupied in one output only, or its positions differ by more than ``POINT_TOL_M``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from msdnet.export.graphs import encoder_tensors, graph_modules
from msdnet.runtime.engine.decode import decode_occupancy
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.spec.grid import GridConfig
from msdnet.training.config import ModelConfig
from msdnet.training.data.batch import make_encoder_input

GRAPH_REL_TOL = 1e-4  # FAIL when a graph's max_rel exceeds this (the goal of the export)
GRAPH_COS_TOL = 1e-6  # FAIL when a graph's cosine similarity is below 1 - this
POINT_TOL_M = 1e-3  # end to end: points further apart than this count as different (metres)
E2E_DIFF_TOL = 0.002  # FAIL when more than this fraction of output points differ end to end


@dataclass
class GraphCheck:
    """Worst-case agreement of one graph over the verification inputs."""

    file: str  # graph file name
    max_abs: float = 0.0  # max |onnx - torch|
    max_rel: float = 0.0  # max |onnx - torch| / max |torch|
    cosine: float = 1.0  # min cosine similarity over inputs

    @property
    def ok(self) -> bool:
        return self.max_rel <= GRAPH_REL_TOL and self.cosine >= 1.0 - GRAPH_COS_TOL

    def add(self, ort_out: np.ndarray, ref: np.ndarray) -> None:
        """Fold one (onnx output, torch output) pair into the worst case."""
        a, b = ort_out.astype(np.float64).ravel(), ref.astype(np.float64).ravel()
        diff = float(np.max(np.abs(a - b))) if a.size else 0.0
        scale = float(np.max(np.abs(b))) if b.size else 0.0
        norm = float(np.linalg.norm(a) * np.linalg.norm(b))
        cos = float(a @ b / norm) if norm > 0 else (1.0 if diff == 0 else 0.0)
        self.max_abs = max(self.max_abs, diff)
        self.max_rel = max(self.max_rel, diff / scale if scale > 0 else diff)
        self.cosine = min(self.cosine, cos)


@dataclass
class EndToEnd:
    """Point counts of both paths and how many points differ, summed over frames."""

    frames: int = 0  # frames compared
    steps: int = 0  # DDIM steps per frame
    points_torch: int = 0  # output points of the torch loop
    points_onnx: int = 0  # output points of the runtime Pipeline
    differ: int = 0  # points in one output only, or further apart than POINT_TOL_M
    max_shift: float = 0.0  # largest distance between matched points (metres)

    @property
    def ok(self) -> bool:
        limit = E2E_DIFF_TOL * max(self.points_torch, self.points_onnx)
        return self.frames > 0 and self.differ <= limit


@dataclass
class VerifyReport:
    """Everything ``--verify`` measured."""

    source: str  # where the frames came from
    graphs: list[GraphCheck]  # per graph, pipeline order
    e2e: EndToEnd  # end to end

    @property
    def ok(self) -> bool:
        return all(g.ok for g in self.graphs) and self.e2e.ok

    def lines(self) -> list[str]:
        """Human-readable table, one line per graph, then end to end."""
        out = [
            f"verify on {self.source} (tolerances: rel <= {GRAPH_REL_TOL:g}, "
            f"cosine >= 1 - {GRAPH_COS_TOL:g}, end-to-end differ <= {E2E_DIFF_TOL:.1%})",
            f"  {'graph':<20} {'max abs':>10} {'max rel':>10} {'cosine':>12}  result",
        ]
        for g in self.graphs:
            out.append(
                f"  {g.file:<20} {g.max_abs:>10.2e} {g.max_rel:>10.2e} {g.cosine:>12.9f}  "
                + ("ok" if g.ok else "FAIL")
            )
        e = self.e2e
        out.append(
            f"  end to end: {e.frames} frames x {e.steps} steps: torch {e.points_torch} points, "
            f"onnxruntime {e.points_onnx} points, {e.differ} differ, max shift {e.max_shift:.2e} m  "
            + ("ok" if e.ok else "FAIL")
        )
        return out

    def to_dict(self) -> dict[str, object]:
        """For the manifest."""
        return {
            "source": self.source,
            "ok": self.ok,
            "graphs": [
                {"file": g.file, "max_abs": g.max_abs, "max_rel": g.max_rel, "cosine": g.cosine}
                for g in self.graphs
            ],
            "end_to_end": {k: getattr(self.e2e, k) for k in EndToEnd.__dataclass_fields__},
            "tolerances": {"graph_rel": GRAPH_REL_TOL, "graph_cos": GRAPH_COS_TOL, "e2e": E2E_DIFF_TOL},
        }


def _voxel_keys(points: np.ndarray, grid: GridConfig) -> np.ndarray:
    """points (M, 3) [x, y, z] -> (M,) int64 linear voxel index ``((z * H) + y) * W + x``."""
    lo = np.asarray(grid.point_range[:3], np.float64)
    size = np.asarray(grid.voxel_size, np.float64)
    nx, ny, nz = grid.shape_xyz
    idx = np.floor((points.astype(np.float64) - lo) / size).astype(np.int64)  # (M, 3) [x, y, z]
    idx = np.clip(idx, 0, np.array([nx - 1, ny - 1, nz - 1]))
    return (idx[:, 2] * ny + idx[:, 1]) * nx + idx[:, 0]


def compare_points(a: np.ndarray, b: np.ndarray, grid: GridConfig) -> tuple[int, float]:
    """Two decoded clouds (M, 3) -> (points that differ, max distance of matched points)."""
    ka, kb = _voxel_keys(a, grid), _voxel_keys(b, grid)
    common, ia, ib = np.intersect1d(ka, kb, assume_unique=False, return_indices=True)
    dist = np.linalg.norm(a[ia].astype(np.float64) - b[ib], axis=1) if len(common) else np.zeros(0)
    only = (len(ka) - len(common)) + (len(kb) - len(common))
    return int(only + np.sum(dist > POINT_TOL_M)), float(dist.max()) if dist.size else 0.0


@torch.no_grad()
def verify_artifact(
    model: nn.Module,
    kind: str,
    cfg: ModelConfig,
    folder: Path,
    frames: list[np.ndarray],
    source: str,
    seed: int = 0,
    threads: int | None = None,
) -> VerifyReport:
    """Compare ``model`` (torch) with the artifact in ``folder`` on ``frames``: list of (N, C)
    float32 radar points in ``cfg.radar_columns`` order. ``threads``: onnxruntime intra-op
    threads (None: its default)."""
    pipe = Pipeline.from_dir(folder, threads=threads)
    mods = dict((spec.file, (spec, mod.eval())) for spec, mod in graph_modules(model, kind))
    checks = {f: GraphCheck(f) for f in mods}
    coeffs = pipe.coefficients()  # (T_m, 3) the manifest's default schedule
    rows = sorted({0, len(coeffs) // 2, len(coeffs) - 1})
    e2e = EndToEnd(steps=len(coeffs))

    def run(file: str, feeds: dict[str, np.ndarray], graph_feeds: dict | None = None) -> list[np.ndarray]:
        spec, mod = mods[file]
        ref = mod(*(torch.from_numpy(feeds[n]) for n in spec.inputs))
        ref = ref if isinstance(ref, tuple) else (ref,)
        outs = pipe.sessions[file].run(None, feeds if graph_feeds is None else graph_feeds)
        for o, r in zip(outs, ref, strict=True):
            checks[file].add(o, r.numpy())
        return [r.numpy() for r in ref]

    step_file = onnx_spec.DENOISER_STEP.file if kind == "student" else onnx_spec.R2LDM_STEP.file
    for pts in frames:
        enc = make_encoder_input([pts], cfg.grid, cfg.max_voxels_radar)
        if enc.features.shape[0] == 0:
            continue
        enc_spec = mods[onnx_spec.ENCODER.file][0]  # the published R2LDM's stops at level 2
        feeds = {n: t.numpy() for n, t in zip(enc_spec.inputs, encoder_tensors(enc, enc_spec), strict=True)}
        pairs = "voxel_counts" in (i.name for i in pipe.sessions[onnx_spec.ENCODER.file].get_inputs())
        graph_feeds = pipe.encoder_feeds(pts)[0] if pairs else None  # the pair form's own inputs
        (f_s,) = run(onnx_spec.ENCODER.file, feeds, graph_feeds)
        rng = np.random.default_rng(seed)  # x_T, then the published sampler's re-noising draws
        noise = rng.standard_normal(f_s.shape, dtype=np.float32)
        if kind == "student":
            (x,) = run(onnx_spec.RGFD_ADAPTER.file, {"bev_features": f_s, "noise": noise})
        else:
            x = noise
        for k in range(len(coeffs)):
            t, a_t, a_prev = (coeffs[k, i : i + 1] for i in range(3))  # each (1,) float32
            feeds = {"x_t": x, "t": t, "abar_t": a_t, "abar_prev": a_prev}
            if kind == "r2ldm":
                feeds["cond"] = f_s
            spec, mod = mods[step_file]
            if k in rows:
                (x,) = run(step_file, feeds)
            else:
                x = mod(*(torch.from_numpy(feeds[n]) for n in spec.inputs)).numpy()
        run(onnx_spec.RECON_HEAD.file, {"features": x})
        if onnx_spec.RECON_HEAD_SPARSE.file in pipe.sessions:  # gate 0: every half-scale voxel
            run(onnx_spec.RECON_HEAD_SPARSE.file, {"features": x, "gate": np.zeros(1, np.float32)})
        # End to end, torch side: the model's own inference path, same noise and step count.
        extra = {"rng": rng} if getattr(model, "takes_rng", False) else {}
        steps = len(coeffs) if pipe.sampler is None else pipe.sampler.steps
        occ, off = model.predict(enc, noise=torch.from_numpy(noise), sample_steps=steps, **extra)
        ref_pts, _ = decode_occupancy(occ[0].numpy(), off[0].numpy(), cfg.grid, pipe.artifact.threshold)
        got = pipe(pts, seed=seed)
        differ, shift = compare_points(ref_pts, got.points, cfg.grid)
        e2e.frames += 1
        e2e.points_torch += len(ref_pts)
        e2e.points_onnx += len(got.points)
        e2e.differ += differ
        e2e.max_shift = max(e2e.max_shift, shift)
    return VerifyReport(source, [checks[s.file] for s in pipe.artifact.specs], e2e)
