"""``--provider auto``'s agreement checks: an engine's outputs against onnxruntime's, held to the
export tolerances (looser ``BF16_*`` ones for bfloat16); the coarse-to-fine head's rows matched
by voxel first, since a voxel whose occupancy sits on the gate may be gated by one engine only."""

from __future__ import annotations

import numpy as np

AGREE_REL_TOL = 1e-4  # = export.verify.GRAPH_REL_TOL (tests/test_provider_auto.py checks)
AGREE_COS_TOL = 1e-6  # = export.verify.GRAPH_COS_TOL
AGREE_E2E_TOL = 0.002  # = export.verify.E2E_DIFF_TOL: voxels gated by one engine only (sparse head)
# auto-bf16: OpenVINO in bfloat16 against onnxruntime f32, a guard against a broken conversion
# (a wrong graph is off by O(1)), not a quality bound (docs/latency.md has the measured gaps).
BF16_REL_TOL = 0.1
BF16_COS_TOL = 1e-3
BF16_E2E_TOL = 0.05


def align_rows(
    got: list[np.ndarray], ref: list[np.ndarray], names: list[str], e2e_tol: float = AGREE_E2E_TOL
) -> tuple[list, list, str | None]:
    """The coarse-to-fine head's outputs (one row per gated voxel, ``voxels`` its ids) on the
    voxels both engines gated: a voxel whose occupancy sits on the gate may fall on either side.
    Up to ``e2e_tol`` of the voxels may be gated by one engine only; else why (one line)."""
    if "voxels" not in names or all(a.shape == b.shape for a, b in zip(got, ref, strict=True)):
        return got, ref, None
    k = names.index("voxels")
    common, ia, ib = np.intersect1d(got[k], ref[k], return_indices=True)
    only = len(got[k]) + len(ref[k]) - 2 * len(common)
    if only > e2e_tol * max(len(got[k]), len(ref[k])):
        return got, ref, f"outputs differ from onnxruntime's: {only} of {len(ref[k])} gated voxels"
    return [a[ia] for a in got], [b[ib] for b in ref], None


def disagreement(
    got: list[np.ndarray], ref: list[np.ndarray], names: list[str] | None = None, precision: str = "f32"
) -> str | None:
    """None when every output agrees within the export tolerances (``precision`` bf16: the
    ``BF16_*`` ones), else why (one line). With ``names`` (output names), gated rows are matched
    first (:func:`align_rows`)."""
    bf16 = precision == "bf16"
    rel_tol, cos_tol = (BF16_REL_TOL, BF16_COS_TOL) if bf16 else (AGREE_REL_TOL, AGREE_COS_TOL)
    got, ref, why = align_rows(got, ref, names or [], BF16_E2E_TOL if bf16 else AGREE_E2E_TOL)
    if why is not None:
        return why
    for a, b in zip(got, ref, strict=True):
        if a.shape != b.shape:
            return f"outputs differ from onnxruntime's: shape {a.shape} != {b.shape}"
        x, y = a.astype(np.float64).ravel(), b.astype(np.float64).ravel()
        if not x.size:
            continue
        diff, scale = float(np.max(np.abs(x - y))), float(np.max(np.abs(y)))
        rel = diff / scale if scale > 0 else diff
        norm = float(np.linalg.norm(x) * np.linalg.norm(y))
        cos = float(x @ y / norm) if norm > 0 else (1.0 if diff == 0 else 0.0)
        if rel > rel_tol or cos < 1.0 - cos_tol:
            return f"outputs differ from onnxruntime's: max rel {rel:.2e}, cosine {cos:.9f}"
    return None
