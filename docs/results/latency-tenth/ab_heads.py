"""Interleaved timing of head graphs on the same real loop features, 2 threads (tenth cycle).

The ninth cycle's gated coarse-to-fine head of ``astyx-lite`` (the 1/2 input norm's statistics from
every 1/4 voxel's up-sampled rows), the tenth's (the same statistics from the rows' sum and Gram
matrix, only the parents' rows up-sampled; what ``models/astyx-lite`` ships now) and the dense
head, each in onnxruntime and OpenVINO, on the loop features of the 53 selection-slice frames
(``runs/v13/feats.py`` wrote them from the shipped model), with the ninth cycle's script
(``docs/results/latency-ninth/ab_heads.py``): each graph on each frame in turn, ``PASSES`` passes,
every other pass in reverse order; medians and 10th percentiles. Run from the repository root.
"""

from __future__ import annotations

import os
import runpy

GATE = 0.2856  # astyx-lite's manifest gate
GRAPHS = {  # name: (graph, gate or None for the dense head)
    "ninth gated c2f": ("runs/v14/ninth-recon_head_sparse.onnx", GATE),  # git show c03c3ac:models/...
    "tenth gated c2f (Gram)": ("models/astyx-lite/recon_head_sparse.onnx", GATE),
    "dense": ("models/astyx-lite/recon_head.onnx", None),
}

if __name__ == "__main__":
    ninth = runpy.run_path("docs/results/latency-ninth/ab_heads.py")
    ninth["main"](GRAPHS, passes=int(os.environ.get("PASSES", "3")), swap=True)
