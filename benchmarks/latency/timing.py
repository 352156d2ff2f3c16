"""Timed pieces of ``msdnet-bench latency``: pipeline stages, the bare step graph, torch eager, the
voxelizer, the peak memory of an ``msdnet-infer`` process.

Every timing is wall time (``time.perf_counter``) after untimed warm-up calls; summaries are the
median and the 90th percentile in milliseconds. Inputs are seeded, so two runs time the same work.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from msdnet.benchmarks.numpy_reference import down_rulebook_numpy, subm_rulebook_numpy, voxelize_numpy
from msdnet.runtime.engine.decode import unpack_children
from msdnet.runtime.engine.kernels import warmup as numba_warmup
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.engine.rulebook import batch_coords, build_encoder_rulebooks
from msdnet.runtime.engine.voxelize import voxelize
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.providers.session import device_of
from msdnet.runtime.spec.grid import GridConfig
from msdnet.training.data.batch import make_encoder_input

Scan = np.ndarray | PointCloud  # (N, C) float32 in the model's columns, or a named cloud
# results.json stage key -> Pipeline.timings keys summed into it
STAGES: dict[str, tuple[str, ...]] = {
    "voxelize_rulebooks": ("prepare", "voxelize"),
    "encoder": ("encoder",),
    "rgfd_adapter": ("adapter",),  # R2LDM: drawing x_T = eps (no adapter)
    "ddim_loop": ("denoise",),
    "recon_head": ("head",),
    "decode": ("decode",),
    "total": ("total",),
}
# typical (mean, std) of the non-geometric radar columns (VoD / Astyx units)
COLUMN_STATS: dict[str, tuple[float, float]] = {
    "rcs": (-12.0, 8.0),  # dBsm
    "v_r": (0.0, 2.0),  # m/s
    "v_r_compensated": (0.0, 1.0),  # m/s
    "mag": (50.0, 8.0),  # Astyx magnitude
    "time": (0.0, 0.0),  # s, single scan
}


def summary(seconds: Sequence[float]) -> dict[str, float]:
    """{"median", "p90", "min"} in ms and "n" (samples) of wall times in seconds."""
    ms = np.asarray(seconds, dtype=np.float64) * 1e3
    return {
        "median": float(np.median(ms)),
        "p90": float(np.percentile(ms, 90)),
        "min": float(ms.min()),
        "n": int(ms.size),
    }


def timed(fn: Callable[[], object], repeats: int, warmup: int = 1) -> list[float]:
    """Seconds per call of ``fn()`` over ``repeats`` calls after ``warmup`` untimed calls."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def synthetic_radar(columns: Sequence[str], grid: GridConfig, n: int = 300, seed: int = 0) -> np.ndarray:
    """(n, C) float32 radar-like scan in ``columns`` order: x y z uniform over the grid box grown
    by 5 % per side (a few points fall outside, as in real scans), other columns ~ COLUMN_STATS."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(grid.point_range[:3]), np.asarray(grid.point_range[3:])
    pad = 0.05 * (hi - lo)
    pts = np.zeros((n, len(columns)), np.float64)
    pts[:, :3] = rng.uniform(lo - pad, hi + pad, size=(n, 3))  # (n, 3) [x, y, z]
    for j, name in enumerate(columns[3:], start=3):
        mean, std = COLUMN_STATS.get(name, (0.0, 1.0))
        pts[:, j] = rng.normal(mean, std, size=n)
    return pts.astype(np.float32)


def calibrate_threshold(pipe: Pipeline, points: Scan, target: int, seed: int = 0) -> float:
    """Occupancy threshold that leaves about ``target`` decoded points on ``points``: one run at a
    near-zero threshold, then the (target + 1)-th largest occupancy (also warms the pipeline)."""
    conf = pipe(points, threshold=1e-6, seed=seed).confidence  # (M,) occupancy of the kept voxels
    if conf.size <= target:
        return 1e-6
    thr = float(np.partition(conf, conf.size - target - 1)[conf.size - target - 1])
    return min(max(thr, 1e-6), 1.0 - 1e-6)


@dataclass
class StageRuns:
    """Per-stage wall times of repeated pipeline calls on one input."""

    seconds: dict[str, list[float]] = field(default_factory=dict)  # STAGES key -> per call
    decoded: int = 0  # points decoded by the last call
    stats: dict[str, int] = field(default_factory=dict)  # Result.stats of the last call

    def summaries(self) -> dict[str, dict[str, float]]:
        return {k: summary(v) for k, v in self.seconds.items()}

    def add(self, later: StageRuns) -> None:
        """Append ``later``'s calls; its decoded points and stats become the last call's."""
        for k, v in later.seconds.items():
            self.seconds.setdefault(k, []).extend(v)
        self.decoded, self.stats = later.decoded, later.stats


def time_stages(
    pipe: Pipeline, points: Scan, steps: int | None, threshold: float | None, repeats: int, seed: int = 0
) -> StageRuns:
    """Run ``pipe`` ``repeats`` times (already warm) and collect the STAGES times."""
    runs = StageRuns({k: [] for k in STAGES})
    for _ in range(repeats):
        res = pipe(points, steps=steps, threshold=threshold, seed=seed)
        for key, parts in STAGES.items():
            runs.seconds[key].append(sum(res.timings.get(p, 0.0) for p in parts))
        runs.decoded, runs.stats = len(res.points), dict(res.stats)
    return runs


class BareStep:
    """The step graph of a pipeline alone: IOBinding, fixed inputs, nothing else per call."""

    def __init__(self, pipe: Pipeline) -> None:
        spec = onnx_spec.DENOISER_STEP if pipe.kind == "student" else onnx_spec.R2LDM_STEP
        self.file = spec.file  # the step graph's file name in the artifact
        self._sess = pipe.sessions[spec.file]
        dev = device_of(pipe.provider)
        rng = np.random.default_rng(0)

        def val(arr: np.ndarray) -> ort.OrtValue:
            return ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(arr, np.float32), dev, 0)

        bev = list(pipe.bev_shape)  # (1, C, H, W)
        row = pipe.coefficients()[0]  # (3,) [t, abar_t, abar_prev]
        self._vals = {"x_t": val(rng.standard_normal(bev)), "cond": val(rng.standard_normal(bev))}
        self._vals |= {k: val(row[i : i + 1]) for i, k in enumerate(("t", "abar_t", "abar_prev"))}
        self._vals["x_prev"] = ort.OrtValue.ortvalue_from_shape_and_type(bev, np.float32, dev, 0)
        self._bind = self._sess.io_binding()
        for name in spec.inputs:
            self._bind.bind_ortvalue_input(name, self._vals[name])
        self._bind.bind_ortvalue_output("x_prev", self._vals["x_prev"])

    def run(self, calls: int) -> float:
        """Seconds for ``calls`` back-to-back runs of the step graph."""
        t0 = time.perf_counter()
        for _ in range(calls):
            self._sess.run_with_iobinding(self._bind)
        return time.perf_counter() - t0

    def seconds(self, repeats: int, warmup: int = 2) -> list[float]:
        """Seconds per single call, ``repeats`` samples after ``warmup`` untimed calls."""
        self.run(warmup)
        return [self.run(1) for _ in range(repeats)]


@dataclass(frozen=True, eq=False)
class PlainRun:
    """The pipeline's graphs run with plain ``session.run`` (numpy in, numpy out)."""

    occupancy: np.ndarray  # (D, H, W) float32
    step_feeds: list[dict[str, np.ndarray]]  # step-graph inputs of every loop step, in order


def plain_run(pipe: Pipeline, points: Scan, steps: int | None = None, seed: int = 0) -> PlainRun:
    """The same arithmetic as ``pipe(points, steps, seed=seed)`` without IOBinding, keeping every
    step's inputs (INT8 calibration data). Noise: ``default_rng(seed)`` as the pipeline draws it."""
    feeds, _, _ = pipe.encoder_feeds(pipe.select_columns(points))  # either encoder form's inputs
    (f_s,) = pipe.sessions[onnx_spec.ENCODER.file].run(None, feeds)  # (1, C, H, W)
    noise = np.random.default_rng(seed).standard_normal(pipe.bev_shape, dtype=np.float32)
    if pipe.kind == "student":
        (x,) = pipe.sessions[onnx_spec.RGFD_ADAPTER.file].run(None, {"bev_features": f_s, "noise": noise})
        spec = onnx_spec.DENOISER_STEP
    else:
        x, spec = noise, onnx_spec.R2LDM_STEP
    step = pipe.sessions[spec.file]
    recorded = []
    for row in pipe.coefficients(steps):
        feed = {"x_t": x, "cond": f_s, "t": row[0:1], "abar_t": row[1:2], "abar_prev": row[2:3]}
        feed = {k: feed[k] for k in spec.inputs}
        recorded.append(feed)
        (x,) = step.run(None, feed)
    occ, _ = pipe.sessions[onnx_spec.RECON_HEAD.file].run(None, {"features": x})
    return PlainRun(unpack_children(occ[0], pipe.artifact.grid.shape_zyx), recorded)


def torch_eager(
    model: torch.nn.Module,
    pipe: Pipeline,
    points: Scan,
    steps: int | None,
    threads: int,
    repeats: int,
    seed: int = 0,
) -> tuple[list[float], np.ndarray]:
    """Seconds per torch forward (encoder -> adapter -> loop -> head; voxels and rulebooks built
    beforehand, as the ORT graph stages exclude them) and its occupancy (D, H, W), with
    ``torch.set_num_threads(threads)``, ``inference_mode`` and the pipeline's noise."""
    art = pipe.artifact
    inp = make_encoder_input([pipe.select_columns(points)], art.grid, art.inputs.max_voxels)
    noise = torch.from_numpy(np.random.default_rng(seed).standard_normal(pipe.bev_shape, dtype=np.float32))
    n_steps = steps if steps is not None else art.diffusion.sample_steps
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    out: dict[str, torch.Tensor] = {}

    def forward() -> None:
        out["occ"] = model.predict(inp, noise, sample_steps=n_steps)[0]

    try:
        with torch.inference_mode():
            seconds = timed(forward, repeats, warmup=1)
    finally:
        torch.set_num_threads(before)
    return seconds, out["occ"][0].numpy()


def voxelize_figures(grid: GridConfig, columns: int, max_voxels: int, repeats: int) -> dict[str, float]:
    """Median ms of a 300-point radar scan through the voxelizer alone and through voxelizer +
    every encoder rulebook, and of a 100k-point LiDAR-like cloud through the voxelizer: numba
    against the numpy references, with the speedups (numpy / numba)."""
    numba_warmup()
    pts = synthetic_radar(("x", "y", "z", *[f"f{i}" for i in range(3, columns)]), grid, 300, seed=1)

    def rulebooks(vox: Callable, subm: Callable, down: Callable | None) -> None:
        coords = batch_coords([vox(pts, grid, max_voxels).coords])  # (V, 4) [b, z, y, x]
        if down is None:  # numba: all levels in one call
            subm(coords, grid.shape_zyx, onnx_spec.NUM_DOWN)
            return
        level, shape = coords, grid.shape_zyx
        for _ in range(onnx_spec.NUM_DOWN):
            subm(level, shape)
            level, _, shape = down(level, shape)
        subm(level, shape)

    reps_np = max(3, repeats // 3)
    fig = {
        "numba_ms": timed(lambda: voxelize(pts, grid, max_voxels), repeats, warmup=2),
        "numpy_ms": timed(lambda: voxelize_numpy(pts, grid, max_voxels), reps_np),
        "numba_with_rulebooks_ms": timed(
            lambda: rulebooks(voxelize, build_encoder_rulebooks, None), repeats, warmup=2
        ),
        "numpy_with_rulebooks_ms": timed(
            lambda: rulebooks(voxelize_numpy, subm_rulebook_numpy, down_rulebook_numpy), reps_np
        ),
    }
    from msdnet.benchmarks.voxelize_bench import lidar_like_cloud

    big = lidar_like_cloud(100000, np.random.default_rng(2))  # (N, 4) [x, y, z, intensity]
    fig["numba_100k_ms"] = timed(lambda: voxelize(big, grid, 60000), max(3, repeats // 3))
    fig["numpy_100k_ms"] = timed(lambda: voxelize_numpy(big, grid, 60000), 3)
    out: dict[str, float] = {"points": 300}
    out |= {k: float(np.median(v) * 1e3) for k, v in fig.items()}
    out["speedup_100k"] = out["numpy_100k_ms"] / out["numba_100k_ms"]
    out["speedup"] = out["numpy_ms"] / out["numba_ms"]
    out["speedup_with_rulebooks"] = out["numpy_with_rulebooks_ms"] / out["numba_with_rulebooks_ms"]
    return out


def infer_command() -> list[str]:
    """How to start ``msdnet-infer``: the installed script next to this Python, else its main."""
    script = Path(sys.executable).parent / "msdnet-infer"
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-c", "from msdnet.runtime.frontends.infer.cli import main; main()"]


# Runs in a fresh, small Python: starts msdnet-infer, waits, prints its peak RSS. Linux keeps a
# process's ru_maxrss across execve, so a child forked straight from this (large) benchmark process
# would report our own size; a small intermediary forks a child whose peak is its own.
_RSS_PROBE = """
import json, resource, subprocess, sys
r = subprocess.run(sys.argv[1:], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
print(json.dumps({"rc": r.returncode, "maxrss_kb": peak, "tail": r.stdout.decode(errors="replace")[-300:]}))
"""


def peak_rss_mb(
    model: Path, points: np.ndarray, columns: Sequence[str], threads: int, threshold: float
) -> float:
    """Peak resident memory (MiB) of one ``msdnet-infer`` process densifying ``points`` (N, C)
    (``columns`` names them; saved as a structured .npy): ``resource.getrusage(RUSAGE_CHILDREN)``
    read in a small intermediary process (see ``_RSS_PROBE``)."""
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "scan.npy"
        table = np.zeros(len(points), dtype=[(c, np.float32) for c in columns])
        for j, name in enumerate(columns):
            table[name] = points[:, j]
        np.save(src, table)
        cmd = [*infer_command(), str(src), "--model", str(model), "--out", str(Path(tmp) / "out")]
        cmd += ["--threads", str(threads), "--threshold", f"{threshold:.9g}"]
        env = {**os.environ, "TQDM_DISABLE": "1"}
        probe = subprocess.run(
            [sys.executable, "-c", _RSS_PROBE, *cmd], capture_output=True, text=True, env=env, check=False
        )
    try:
        report = json.loads(probe.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        raise RuntimeError(f"memory probe failed: {probe.stderr.strip()[-300:]}") from None
    if report["rc"] != 0:
        raise RuntimeError(f"msdnet-infer exited {report['rc']}: {report['tail'].strip()}")
    return report["maxrss_kb"] / 1024.0  # Linux reports kB
