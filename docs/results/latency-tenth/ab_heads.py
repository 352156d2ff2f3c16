"""Interleaved timing of head graphs on the same real loop features, 2 threads (tenth cycle).

The ninth cycle's gated coarse-to-fine head of ``astyx-lite`` (the 1/2 input norm's statistics from
every 1/4 voxel's up-sampled rows), the tenth's (the same statistics from the rows' sum and Gram
matrix, only the parents' rows up-sampled; what ``models/astyx-lite`` ships now) and the dense
head, each in onnxruntime and OpenVINO, on the loop features of the 53 selection-slice frames
(``runs/v13/feats.py`` wrote them from the shipped model). Each graph runs on each frame in turn,
``PASSES`` passes; medians and 10th percentiles. Run from the repository root.
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
GATE = 0.2856  # astyx-lite's manifest gate
GRAPHS = {  # name: (graph, gate or None for the dense head)
    "ninth gated c2f": ("runs/v14/ninth-recon_head_sparse.onnx", GATE),  # git show c03c3ac:models/...
    "tenth gated c2f (Gram)": ("models/astyx-lite/recon_head_sparse.onnx", GATE),
    "dense": ("models/astyx-lite/recon_head.onnx", None),
}
PASSES = int(os.environ.get("PASSES", "3"))


def feeds(f: np.ndarray, gate: float | None) -> dict[str, np.ndarray]:
    out = {"features": f[None]}
    if gate is not None:
        out["gate"] = np.array([gate], np.float32)
    return out


def runners() -> dict[str, Callable[[np.ndarray], object]]:
    out: dict[str, Callable[[np.ndarray], object]] = {}
    core = ov.Core()
    for name, (path, gate) in GRAPHS.items():
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


def main() -> None:
    frames = np.load(FEATURES)["feats"][299:352]
    run = runners()
    for f in frames[:3]:  # warm-up
        for r in run.values():
            r(f)
    times: dict[str, list[float]] = {k: [] for k in run}
    for p in range(PASSES):
        order = list(run.items()) if p % 2 == 0 else list(run.items())[::-1]
        for f in frames:
            for k, r in order:
                t0 = time.perf_counter()
                r(f)
                times[k].append(time.perf_counter() - t0)
    for k, v in times.items():
        print(f"{k:40s} median {np.median(v) * 1e3:6.2f} ms  p10 {np.percentile(v, 10) * 1e3:6.2f}")


if __name__ == "__main__":
    main()
