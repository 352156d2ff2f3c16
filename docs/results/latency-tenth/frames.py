"""Per-stage medians of ``models/astyx-lite`` over the 53 selection-slice Astyx frames (000299-000351,
two passes after three warm-up frames), 2 threads, one provider per process (``cpu-shared``'s pool is
the process's). Run from the repository root, alternating providers:

    for i in 1 2 3; do for p in cpu cpu-shared auto; do
        python docs/results/latency-tenth/frames.py $p; done; done
"""

from __future__ import annotations

import os
import sys

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

import numpy as np  # noqa: E402

from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402
from msdnet.runtime.io.datasets import open_dataset  # noqa: E402


def stage_medians(pipe: Pipeline) -> str:
    """Per-stage medians (ms) of ``pipe`` over the slice frames, one line."""
    ds = open_dataset("astyx", "../shared/data/astyx_hires2019", split="train")
    frames = [ds.load(i).radar for i in ds.frame_ids[299:352]]
    for f in frames[:3]:
        pipe(f, seed=0)
    seconds: dict[str, list[float]] = {}
    for _ in range(2):
        for f in frames:
            for stage, s in pipe(f, seed=0).timings.items():
                seconds.setdefault(stage, []).append(s)
    return " ".join(f"{k} {np.median(v) * 1e3:.2f}" for k, v in seconds.items() if k != "prepare")


if __name__ == "__main__":
    print(f"{sys.argv[1]:10s} ms: {stage_medians(Pipeline.from_dir('models/astyx-lite', sys.argv[1], 2))}")
