"""Loop features of a model's selection-slice frames, the input the head graphs are timed on
(eleventh cycle). The shipped model runs each radar scan of the slice its checkpoint recorded
(seed 0, its default steps); the final loop buffer is the head's ``features``. Encoder, RGFD,
adapter and loop are the same weights in every head variant timed, so one dump serves all.

Run from the repository root (writes ``feats`` (frames, C, H8, W8) float32 to OUT.npz):

    python docs/results/latency-eleventh/feats.py models/astyx-lite CKPT astyx \
        ../shared/data/astyx_hires2019 runs/v15/astyx-select-feats.npz   # 53 frames
    python docs/results/latency-eleventh/feats.py models/sim-lite CKPT sim data/sim \
        runs/v15/sim-select-feats.npz                                     # 24 frames

CKPT: the model's training checkpoint (or one ``training.recover`` read back from its graphs with
``--holdout``): it fixes the slice.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

import numpy as np  # noqa: E402

from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402
from msdnet.training.checkpoint import load_checkpoint  # noqa: E402
from msdnet.training.data import run_splits  # noqa: E402


def slice_features(model: str, checkpoint: str, dataset: str, root: str) -> np.ndarray:
    """(frames, C, H8, W8) loop features of the checkpoint's selection slice through ``model``."""
    _, cfg, state = load_checkpoint(checkpoint)
    _, select = run_splits(dataset, root, cfg, state.dataset)
    pipe = Pipeline.from_dir(model, threads=2)
    pipe.gate = None  # the dense head: the features do not depend on it
    final = pipe.coefficients().shape[0] % 2  # the loop's final ping-pong buffer
    feats = []
    for i in range(len(select)):
        pipe(np.ascontiguousarray(select[i][0], np.float32))  # (N, C) in the model's columns
        feats.append(pipe._x[final].numpy()[0].copy())  # (C, H8, W8)
    return np.stack(feats)


if __name__ == "__main__":
    model, checkpoint, dataset, root, out = sys.argv[1:6]
    feats = slice_features(model, checkpoint, dataset, root)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, feats=feats)
    print(f"{out}: {feats.shape}")
