"""Interleaved timing of head graphs on the same real loop features (eleventh cycle).

The shipped gated coarse-to-fine head of ``models/astyx-lite`` (tenth cycle: sparse from 1/2 down),
the gated8 ones retrained this cycle (sparse from 1/4 down) and the dense head, each in the
sessions the runtime itself builds (``runtime.engine.session.create_session``: onnxruntime's CPU
provider with its intra-op pool not spinning, and OpenVINO), at 1 and 2 threads, on the loop
features of the 53 selection-slice frames (``feats.py`` here wrote them from the shipped model).
Each graph runs on each frame in turn, ``PASSES`` passes, every other pass in reverse order;
medians and 10th percentiles, and each median over the best dense median.

The ninth and tenth cycles' script (``docs/results/latency-ninth/ab_heads.py``) built plain
sessions whose idle onnxruntime pools spin: with several sessions in one process they took the
cores from each other, and its onnxruntime medians of the coarse-to-fine graphs were 1.7-1.9x the
runtime's (the same graph on the same frames: 17-19 ms there, 10 ms in ``Pipeline``).

Run from the repository root: ``python docs/results/latency-eleventh/ab_heads.py SHIPPED_DIR
GATED8_DIR...`` (the dense head is SHIPPED_DIR's); ``FEATURES=PATH.npz`` times other features
(``feats.py`` writes them for any model's slice).
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

import numpy as np  # noqa: E402

from msdnet.runtime.engine.session import create_session  # noqa: E402

FEATURES = os.environ.get("FEATURES", "runs/v15/astyx-select-feats.npz")  # (53, 64, 20, 20), feats.py
ENGINES = {"onnxruntime": "cpu", "openvino": "openvino"}  # name: runtime provider


def graphs(shipped: Path, gated8: list[Path]) -> dict[str, tuple[Path, float | None]]:
    """name: (graph, gate or None for the dense head), gates from each model's manifest."""

    def gate(folder: Path) -> float:
        return json.loads((folder / "manifest.json").read_text())["gate"]

    out = {f"{shipped.name} c2f": (shipped / "recon_head_sparse.onnx", gate(shipped))}
    out |= {f"{g.name} c2f": (g / "recon_head_sparse.onnx", gate(g)) for g in gated8}
    return out | {"dense": (shipped / "recon_head.onnx", None)}


def runners(heads: dict[str, tuple[Path, float | None]], threads: tuple[int, ...]) -> dict[str, Callable]:
    """'name / engine / N threads': a call on one (C, H8, W8) feature map."""
    out: dict[str, Callable] = {}
    for name, (path, gate) in heads.items():
        for engine, provider in ENGINES.items():
            for t in threads:
                sess = create_session(path.read_bytes(), path.name, provider, t)
                feeds = {} if gate is None else {"gate": np.array([gate], np.float32)}
                out[f"{name} / {engine} / {t}"] = lambda f, s=sess, e=feeds: s.run(
                    None, {"features": f[None], **e}
                )
    return out


def main(shipped: Path, gated8: list[Path], passes: int, threads: tuple[int, ...]) -> None:
    frames = np.load(FEATURES)["feats"]
    run = runners(graphs(shipped, gated8), threads)
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
        print(f"{k:48s} median {med * 1e3:6.2f} ms  p10 {p10 * 1e3:6.2f}  / best dense {med / dense:.3f}")


if __name__ == "__main__":
    passes = int(os.environ.get("PASSES", "3"))
    threads = tuple(int(t) for t in os.environ.get("THREADS", "1,2").split(","))
    main(Path(sys.argv[1]), [Path(a) for a in sys.argv[2:]], passes, threads)
