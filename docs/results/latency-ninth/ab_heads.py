"""Interleaved timing of head graphs on the same real loop features, 2 threads (ninth cycle).

The eighth cycle's coarse-to-fine head (dense trunk to 1/2), the gated one, the gated one with its
1/2 conv over 4x4x4 blocks (not shipped) and the dense head, each in onnxruntime and OpenVINO, on
the loop features of the 53 selection-slice frames (``runs/v13/feats.py`` wrote them from the
shipped model: encoder, RGFD, adapter and loop are the same in every variant). Each graph runs on
each frame in turn, two passes; medians and 10th percentiles. Run from the repository root.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

import numpy as np  # noqa: E402
import onnxruntime as ort  # noqa: E402
import openvino as ov  # noqa: E402

FEATURES = "runs/v13/astyx-train.npz"  # (352, 64, 20, 20) loop features of frames 000000-000351
GRAPHS = {  # name: (graph, gate or None for the dense head)
    "eighth c2f": ("runs/v13/shipped-astyx-lite/recon_head_sparse.onnx", 0.6121),
    "gated c2f rows": ("models/astyx-lite/recon_head_sparse.onnx", 0.2856),
    "gated c2f blocks": ("runs/v13/astyx-blocks/recon_head_sparse.onnx", 0.2856),
    "dense": ("models/astyx-lite/recon_head.onnx", None),
}


def feeds(f: np.ndarray, gate: float | None) -> dict[str, np.ndarray]:
    out = {"features": f[None]}
    if gate is not None:
        out["gate"] = np.array([gate], np.float32)
    return out


def runners(graphs: dict[str, tuple[str, float | None]]) -> dict[str, Callable[[np.ndarray], object]]:
    out: dict[str, Callable[[np.ndarray], object]] = {}
    core = ov.Core()
    for name, (path, gate) in graphs.items():
        so = ort.SessionOptions()
        so.intra_op_num_threads, so.inter_op_num_threads = 2, 1
        sess = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
        out[f"{name} / onnxruntime"] = lambda f, s=sess, g=gate: s.run(None, feeds(f, g))
        compiled = core.compile_model(
            path, "CPU", {"INFERENCE_NUM_THREADS": 2, "INFERENCE_PRECISION_HINT": "f32"}
        )
        req = compiled.create_infer_request()
        out[f"{name} / openvino"] = lambda f, r=req, g=gate: r.infer(feeds(f, g))
    return out


def main(graphs: dict[str, tuple[str, float | None]] = GRAPHS, passes: int = 2, swap: bool = False) -> None:
    """Time ``graphs`` on the frames, ``passes`` passes (``swap``: every other pass in reverse order)."""
    frames = np.load(FEATURES)["feats"][299:352]
    run = runners(graphs)
    for f in frames[:3]:  # warm-up
        for r in run.values():
            r(f)
    times: dict[str, list[float]] = {k: [] for k in run}
    for p in range(passes):
        order = list(run.items())[::-1] if swap and p % 2 else list(run.items())
        for f in frames:
            for k, r in order:
                t0 = time.perf_counter()
                r(f)
                times[k].append(time.perf_counter() - t0)
    width = max(30, *(len(k) for k in times))
    for k, v in times.items():
        print(f"{k:{width}s} median {np.median(v) * 1e3:6.2f} ms  p10 {np.percentile(v, 10) * 1e3:6.2f}")


if __name__ == "__main__":
    main()
