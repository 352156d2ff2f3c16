"""Interleaved timing of head graphs on the same real loop features, 2 threads (eleventh cycle).

The shipped gated coarse-to-fine head of ``models/astyx-lite`` (tenth cycle: sparse from 1/2 down),
the gated8 one retrained this cycle (sparse from 1/4 down) and the dense head, each in onnxruntime
and OpenVINO, on the loop features of the 53 selection-slice frames (``feats.py`` here wrote them
from the shipped model), with the ninth cycle's runners: each graph on each frame in turn,
``PASSES`` passes, every other pass in reverse order; medians and 10th percentiles. Run from the
repository root: ``python docs/results/latency-eleventh/ab_heads.py GATED8_MODEL_DIR``.
"""

from __future__ import annotations

import json
import os
import runpy
import sys
import time
from pathlib import Path

import numpy as np

FEATURES = "runs/v15/astyx-select-feats.npz"  # (53, 64, 20, 20), feats.py


def graphs(gated8: Path) -> dict[str, tuple[str, float | None]]:
    """name: (graph, gate or None for the dense head), gates from each model's manifest."""
    shipped = json.loads(Path("models/astyx-lite/manifest.json").read_text())["gate"]
    new = json.loads((gated8 / "manifest.json").read_text())["gate"]
    return {
        "shipped gated c2f (tenth)": ("models/astyx-lite/recon_head_sparse.onnx", shipped),
        "gated8 c2f (eleventh)": (str(gated8 / "recon_head_sparse.onnx"), new),
        "dense": ("models/astyx-lite/recon_head.onnx", None),
    }


def main(gated8: Path, passes: int) -> None:
    ninth = runpy.run_path("docs/results/latency-ninth/ab_heads.py")
    frames = np.load(FEATURES)["feats"]
    run = ninth["runners"](graphs(gated8))
    for f in frames[:3]:  # warm-up
        for r in run.values():
            r(f)
    times: dict[str, list[float]] = {k: [] for k in run}
    for p in range(passes):
        order = list(run.items())[::-1] if p % 2 else list(run.items())
        for f in frames:
            for k, r in order:
                t0 = time.perf_counter()
                r(f)
                times[k].append(time.perf_counter() - t0)
    dense = min(np.median(v) for k, v in times.items() if k.startswith("dense"))
    for k, v in times.items():
        med, p10 = np.median(v), np.percentile(v, 10)
        print(f"{k:40s} median {med * 1e3:6.2f} ms  p10 {p10 * 1e3:6.2f}  / best dense {med / dense:.3f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), passes=int(os.environ.get("PASSES", "3")))
