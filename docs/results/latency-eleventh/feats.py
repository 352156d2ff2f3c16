"""Loop features of the 53 Astyx selection-slice frames (000299-000351), the input the head graphs
are timed on (eleventh cycle). The shipped ``models/astyx-lite`` runs each radar scan (seed 0, its
2 steps); the final loop buffer is the head's ``features``. Encoder, RGFD, adapter and loop are the
same weights in every head variant timed, so one dump serves all. Run from the repository root;
writes ``runs/v15/astyx-select-feats.npz`` (feats (53, C, H8, W8) float32).
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

import numpy as np  # noqa: E402

from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402
from msdnet.runtime.io.files import read_cloud  # noqa: E402

RADAR = Path("../shared/data/astyx_hires2019/radar_6455")
OUT = Path("runs/v15/astyx-select-feats.npz")

if __name__ == "__main__":
    pipe = Pipeline.from_dir("models/astyx-lite", threads=2)
    pipe.gate = None  # the dense head: the features do not depend on it
    feats = []
    for i in range(299, 352):
        pipe(read_cloud(RADAR / f"{i:06d}.txt"))
        final = pipe.coefficients().shape[0] % 2  # the loop's final ping-pong buffer
        feats.append(pipe._x[final].numpy()[0].copy())  # (C, H8, W8)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    np.savez(OUT, feats=np.stack(feats))
    print(f"{OUT}: {np.stack(feats).shape}")
