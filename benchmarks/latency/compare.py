"""The runtime against other ways to run the same model: torch eager, and an INT8 step graph."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from msdnet.benchmarks.latency.models import int8_artifact
from msdnet.benchmarks.latency.timing import BareStep, plain_run, summary, time_stages, torch_eager
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.metrics.cloud import chamfer_distance


def torch_comparison(
    model: torch.nn.Module,
    pipe: Pipeline,
    points: Any,
    ort_graph_seconds: np.ndarray,
    threads: int,
    repeats: int,
    seed: int = 0,
) -> dict[str, Any]:
    """torch eager (same weights, inputs and noise; inference_mode) at ``threads`` threads (the
    ratio the goals ask for) and at 1 thread (torch's OpenMP pool spins, which a loaded machine
    punishes), against ``ort_graph_seconds`` (per run: encoder + adapter + loop + head in ORT).
    Also the largest occupancy difference between torch and onnxruntime: proof of the same model."""
    seconds, occ_torch = torch_eager(model, pipe, points, None, threads, repeats, seed)
    out: dict[str, Any] = {"threads": threads, "torch": summary(seconds)}
    if threads != 1:
        out["torch_1_thread"] = summary(torch_eager(model, pipe, points, None, 1, repeats, seed)[0])
    out["onnxruntime_graphs"] = summary(ort_graph_seconds)
    occ_ort = plain_run(pipe, points, None, seed).occupancy  # (D, H, W)
    out["max_abs_occupancy_diff"] = float(np.abs(occ_torch - occ_ort).max())
    best = min(out["torch"]["median"], out.get("torch_1_thread", out["torch"])["median"])
    out["onnx_over_torch"] = out["onnxruntime_graphs"]["median"] / out["torch"]["median"]
    out["onnx_over_best_torch"] = out["onnxruntime_graphs"]["median"] / best
    return out


def int8_comparison(
    pipe: Pipeline,
    points: Any,
    threshold: float,
    scratch: Path,
    threads: int,
    repeats: int,
    frame_repeats: int,
    seed: int = 0,
) -> dict[str, Any]:
    """Quantize the step graph (calibrated on this input's own loop states), then: bare step time
    FP32 vs INT8 (interleaved, ``repeats`` each), a frame's total with INT8 (``frame_repeats``),
    the one-step relative error, and the quality cost on the same input, seed and threshold:
    decoded points and the Chamfer distance (m) of the INT8 cloud to the FP32 cloud."""
    feeds = plain_run(pipe, points, None, seed).step_feeds
    folder = int8_artifact(pipe.artifact.root, scratch / "msdnet-int8", feeds)
    pipe8 = Pipeline.from_dir(folder, provider=pipe.provider, threads=threads)
    bare32, bare8 = BareStep(pipe), BareStep(pipe8)
    bare32.run(2), bare8.run(2)
    s32, s8 = [], []
    for _ in range(repeats):  # interleaved: both see the same load
        s32.append(bare32.run(1))
        s8.append(bare8.run(1))
    pipe8(points, threshold=threshold, seed=seed)  # warm-up
    runs8 = time_stages(pipe8, points, None, threshold, frame_repeats, seed)
    ref = pipe(points, threshold=threshold, seed=seed).points
    got = pipe8(points, threshold=threshold, seed=seed).points
    f32 = pipe.sessions[bare32.file].run(None, feeds[0])[0]
    f8 = pipe8.sessions[bare8.file].run(None, feeds[0])[0]
    return {
        "method": pipe8.artifact.manifest["quantization"]["method"],
        "step_ms_fp32": float(np.median(s32) * 1e3),
        "step_ms_int8": float(np.median(s8) * 1e3),
        "step_speedup": float(np.median(s32) / np.median(s8)),
        "total_ms_int8": runs8.summaries()["total"]["median"],
        "step_rel_error": float(np.linalg.norm(f8 - f32) / np.linalg.norm(f32)),
        "decoded_fp32": len(ref),
        "decoded_int8": len(got),
        "chamfer_int8_vs_fp32_m": chamfer_distance(got, ref),
        "default": False,  # the runtime never picks INT8 by itself
    }
