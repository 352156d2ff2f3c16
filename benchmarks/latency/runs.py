"""Measurement protocols of ``msdnet-bench latency``: the main MSDNet run, interleaved with the
bare step graph (loop overhead, FLOP rate), and the round-robin sweeps over steps and input size."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from tqdm import tqdm

from msdnet.benchmarks.flops import graph_flops
from msdnet.benchmarks.latency.timing import BareStep, StageRuns, summary, time_stages
from msdnet.benchmarks.machine import measure_sgemm_gflops
from msdnet.runtime.engine.pipeline import Pipeline


def msdnet_timings(
    pipe: Pipeline, points: Any, thr: float, repeats: int, warmup: int, seed: int = 0
) -> dict[str, Any]:
    """``repeats`` pipeline calls (after ``warmup``), each followed by a block of T_m bare
    step-graph calls, so both see the same load. -> {"runs": StageRuns, "loop_overhead_share":
    median over the pairs of (loop - block) / loop, "step_graph": times, FLOPs, FLOP rates, and a numpy
    sgemm rate measured right after}."""
    bare = BareStep(pipe)
    n_steps = pipe.artifact.diffusion.sample_steps
    for _ in range(warmup):
        pipe(points, threshold=thr, seed=seed)
    bare.run(n_steps)
    runs, blocks = StageRuns({}), []
    for _ in tqdm(range(repeats), desc="MSDNet stages", unit="frame", disable=None):
        runs.add(time_stages(pipe, points, None, thr, 1, seed))
        blocks.append(bare.run(n_steps))
    loops = np.asarray(runs.seconds["ddim_loop"])  # (repeats,) s, pairs with ``blocks``
    loop, bare_loop = float(np.median(loops)), float(np.median(blocks))
    loop_best, bare_best = min(runs.seconds["ddim_loop"]), min(blocks)  # robust to other load
    step_s, best_s = bare_loop / n_steps, bare_best / n_steps
    sgemm = measure_sgemm_gflops(repeats=20)  # best of 20, right after: under the same load
    bev = pipe.bev_shape
    shapes = {"x_t": bev, "t": (1,), "abar_t": (1,), "abar_prev": (1,)}
    flops = graph_flops(pipe.artifact.root / bare.file, shapes)
    return {
        "runs": runs,
        "loop_overhead_share": float(np.median(1.0 - np.asarray(blocks) / loops)),  # per pair
        "step_graph": {
            "ms": step_s * 1e3,
            "ms_p90": float(np.percentile(blocks, 90)) / n_steps * 1e3,
            "gflop": flops / 1e9,
            "gflops_rate": flops / step_s / 1e9,  # at the median step time
            "gflops_rate_best": flops / best_s / 1e9,  # at the fastest block
            "sgemm_gflops_adjacent": sgemm,
            "steps_per_frame": n_steps,
            "loop_ms": loop * 1e3,
            "bare_loop_ms": bare_loop * 1e3,
            "loop_best_ms": loop_best * 1e3,
            "bare_loop_best_ms": bare_best * 1e3,
            "loop_overhead_share_medians": (loop - bare_loop) / loop,
            "loop_overhead_share_best": (loop_best - bare_best) / loop_best,
        },
    }


def sweep(
    pipe: Pipeline,
    thr: float,
    make: Callable[[int], tuple[Any, int | None]],
    values: tuple[int, ...],
    key: str,
    repeats: int,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Latency for each ``value`` (``make(value)`` -> (points, steps)). One warm-up call per value,
    then the repetitions go round-robin over the values, so a burst of other load hits them all."""
    cases = [make(v) for v in values]
    for points, steps in cases:
        pipe(points, steps=steps, threshold=thr, seed=seed)  # new shapes: warm once
    runs = [StageRuns({}) for _ in values]
    bar = tqdm(total=repeats * len(values), desc=f"{key} sweep", disable=None)
    for _ in range(repeats):
        for (points, steps), acc in zip(cases, runs, strict=True):
            acc.add(time_stages(pipe, points, steps, thr, 1, seed))
            bar.update()
    bar.close()
    rows = []
    for value, acc in zip(values, runs, strict=True):
        s = acc.summaries()
        rows.append(
            {
                key: int(value),
                "ms": s["total"]["median"],
                "p90": s["total"]["p90"],
                "min": s["total"]["min"],
                "loop_ms": s["ddim_loop"]["median"],
                "voxelize_ms": s["voxelize_rulebooks"]["median"],
                "voxels": acc.stats.get("voxels", 0),
                "decoded": acc.decoded,
            }
        )
    return rows


def stream_timings(
    pipe: Pipeline, scans: list[Any], thr: float, seed: int = 0, gate: float | None = None
) -> dict[str, Any]:
    """Whole frames on a stream, as a sensor feeds them: each of ``scans`` once, in order, through
    the warm pipeline as it is set (``pipe.gate``). Every input is new to every session, which
    matters for OpenVINO: it prepares kernels per input shape, and the main run's repeated input
    lets it reuse them (``docs/latency.md``). With a coarse-to-fine ``gate`` (default
    ``pipe.gate``), each frame is then run again with the other head, whose head time alone is kept
    (the second call's other stages have seen the frame). -> {"frames": len(scans), "stages_ms":
    per-stage summaries, "decoded_median", "voxels_median", "head_voxels_median" (medians over the
    frames), and with a gate "heads_ms" ({"coarse-to-fine", "dense"}: head summaries) and
    "head_over_dense_head" (ratio of their medians)}."""
    runs, per = StageRuns({}), {"decoded": [], "voxels": [], "head_voxels": []}
    runs_with = pipe.gate
    gate = runs_with if gate is None else gate
    other = gate if runs_with is None else None  # the head the pipeline does not run
    heads: dict[str, list[float]] = {"coarse-to-fine": [], "dense": []}
    try:
        for scan in tqdm(scans, desc="MSDNet on a stream", unit="frame", disable=None):
            pipe.gate = runs_with
            one = time_stages(pipe, scan, None, thr, 1, seed)
            runs.add(one)
            per["decoded"].append(one.decoded)
            per["voxels"].append(one.stats.get("voxels", 0))
            per["head_voxels"].append(one.stats.get("head_voxels", 0))
            if gate is not None:
                pipe.gate = other
                again = time_stages(pipe, scan, None, thr, 1, seed).seconds["recon_head"][0]
                ran = one.seconds["recon_head"][0]
                heads["coarse-to-fine"].append(ran if runs_with is not None else again)
                heads["dense"].append(again if runs_with is not None else ran)
    finally:
        pipe.gate = runs_with
    out: dict[str, Any] = {"frames": len(scans), "stages_ms": runs.summaries()}
    out |= {f"{k}_median": float(np.median(v)) for k, v in per.items()}
    if gate is not None:
        out["heads_ms"] = {k: summary(v) for k, v in heads.items()}
        out["head_over_dense_head"] = (
            out["heads_ms"]["coarse-to-fine"]["median"] / out["heads_ms"]["dense"]["median"]
        )
    return out
