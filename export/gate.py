"""The coarse-to-fine head's gate, calibrated like the threshold, and adding the sparse head to a model.

The gate is a threshold on each half-scale voxel's own occupancy (the head's 1/2-scale branch):
``recon_head_sparse.onnx`` decodes the full scale only under voxels above it. A gate can only
remove points (those of dropped voxels), so it is chosen on the same held-out training-range
frames as the decoding threshold (``training.recipe.calibrate``: the run's selection slice) as the
LARGEST gate that keeps at least ``recall`` of the points the dense head decodes there at the
manifest's threshold. The runtime itself measures it: the artifact's Pipeline with gate 0 gives
every half-scale voxel's gate occupancy and children's occupancy.

``msdnet-export gate MODEL --checkpoint CKPT --dataset D --data ROOT`` exports the sparse
head of the checkpoint the model came from into the model folder (same weights as its
``recon_head.onnx``, checked on a frame) and writes the calibrated gate into its manifest.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from msdnet.export.manifest_fields import update_manifest
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import MANIFEST, file_digest, load_artifact

RECALL = 0.99  # share of the dense head's points the shipped gate keeps on the calibration frames


def keep_all_gate(occupancy: np.ndarray, gate_occupancy: np.ndarray, threshold: float) -> float:
    """The largest gate that keeps every half-scale voxel with a child above ``threshold``.

    occupancy: (N, 8) children's occupancy; gate_occupancy: (N,) the voxels' own occupancy.
    -> gate in [0, 1) (0.0 when no child is occupied: keep everything)."""
    hit = (np.asarray(occupancy, np.float32) > np.float32(threshold)).any(axis=1)
    if not hit.any():
        return 0.0
    lowest = np.float32(np.asarray(gate_occupancy, np.float32)[hit].min())
    return float(max(np.nextafter(lowest, np.float32(0.0)), np.float32(0.0)))


@dataclass(frozen=True)
class GateCalibration:
    """The chosen gate and what it keeps on the calibration frames (totals over the frames)."""

    gate: float  # half-scale occupancy gate
    recall: float  # share of the dense head's points asked to be kept
    points_kept: float  # share of the dense head's decoded points the gate keeps
    voxels_kept: float  # share of the half-scale voxels decoded at full scale
    keep_all_gate: float  # the largest gate keeping every point (min over the frames)
    frames: int  # calibration frames
    threshold: float  # decoding threshold the points were counted at


def calibrate_gate(
    pipe: Pipeline, scans: Sequence[np.ndarray], threshold: float | None = None, recall: float = RECALL
) -> GateCalibration:
    """Choose the gate on ``scans`` ((N, C) arrays in the manifest's columns) run through ``pipe``
    (its default steps, seed 0); see the module docstring. Leaves ``pipe.gate`` as it was."""
    if not 0.0 < recall <= 1.0:
        raise MsdnetError("recall", f"must be in (0, 1], got {recall}")
    thr = pipe.artifact.threshold if threshold is None else float(threshold)
    gates, counts, keep_all, before = [], [], [], pipe.gate
    pipe.gate = 0.0
    try:
        for scan in tqdm(scans, desc="gate calibration", unit="frame", leave=False):
            if pipe(scan, threshold=thr).stats["voxels"] == 0:
                continue
            out = pipe.sparse_head_outputs()
            in_grid = _children_in_grid(out["voxels"], pipe.artifact.grid.shape_zyx)
            counts.append(((out["occupancy"] > np.float32(thr)) & in_grid).sum(axis=1))
            gates.append(out["gate_occupancy"])
            if counts[-1].any():  # a frame without a point puts no bound on the gate
                keep_all.append(keep_all_gate(out["occupancy"] * in_grid, out["gate_occupancy"], thr))
    finally:
        pipe.gate = before
    if not gates:
        raise MsdnetError(None, "no calibration frame has a voxel inside the grid")
    g, c = np.concatenate(gates), np.concatenate(counts).astype(np.int64)
    order = np.argsort(g, kind="stable")
    lost = np.cumsum(c[order])  # points dropped by a gate at g[order[k]] (ties handled below)
    total = int(c.sum())
    allowed = (1.0 - recall) * total
    gate = 0.0
    for k in np.flatnonzero(lost <= allowed)[::-1]:  # largest gate whose ties all fit the budget
        if k + 1 == len(g) or g[order[k + 1]] > g[order[k]]:
            gate = float(np.floor(float(g[order[k]]) * 1e4) / 1e4)  # rounded down: keeps a bit more
            break
    kept = g > np.float32(gate)
    return GateCalibration(
        gate=gate,
        recall=recall,
        points_kept=float(c[kept].sum() / total) if total else 1.0,
        voxels_kept=float(kept.mean()),
        keep_all_gate=float(min(keep_all)) if keep_all else 0.0,
        frames=len(gates),
        threshold=thr,
    )


def _children_in_grid(voxels: np.ndarray, shape_zyx: Sequence[int]) -> np.ndarray:
    """(N, 8) bool: child ``(dz * 2 + dy) * 2 + dx`` of each half-scale voxel lies inside the grid."""
    d, h, w = shape_zyx
    h2, w2 = (h + 1) // 2, (w + 1) // 2
    x2, y2, z2 = voxels % w2, (voxels // w2) % h2, voxels // (w2 * h2)
    child = np.arange(8)
    z = 2 * z2[:, None] + (child >> 2)
    y = 2 * y2[:, None] + ((child >> 1) & 1)
    x = 2 * x2[:, None] + (child & 1)
    return (z < d) & (y < h) & (x < w)


def add_sparse_head(
    folder: Path, checkpoint: Path, dataset: str, data: Path, frames: int = 24, recall: float = RECALL
) -> GateCalibration:
    """Export ``checkpoint``'s sparse head into the model ``folder`` and calibrate its gate on the
    checkpoint's selection slice (its training ``holdout``); the manifest is rewritten atomically.
    Refuses a checkpoint whose head differs from the folder's ``recon_head.onnx``."""
    import torch

    from msdnet.export.graphs import SparseHeadGraph, example_inputs, export_graph, tracing_points
    from msdnet.training.data.batch import make_encoder_input
    from msdnet.training.data.datasets import run_splits
    from msdnet.training.recipe.calibrate import pick_frames
    from msdnet.training.recipe.checkpoint import load_checkpoint

    art = load_artifact(folder)
    model, cfg, state = load_checkpoint(checkpoint)
    spec = onnx_spec.RECON_HEAD_SPARSE
    enc = make_encoder_input([tracing_points(cfg)], cfg.grid, cfg.max_voxels_radar)
    args = example_inputs(spec, cfg, enc)
    with torch.no_grad():
        ref = model.head.packed(args[0])[0].numpy()  # (1, 8, D2, H2, W2)
    tmp = folder / f".{spec.file}.tmp"
    export_graph(SparseHeadGraph(model.head), args, spec, tmp)
    import onnxruntime as ort

    got = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"]).run(
        None, {"features": args[0].numpy(), "gate": np.zeros(1, np.float32)}
    )[0]
    if not np.allclose(got, ref.reshape(8, -1).T, atol=1e-5):
        tmp.unlink()
        raise MsdnetError(checkpoint, "its head does not reproduce the model's recon_head.onnx")
    os.replace(tmp, folder / spec.file)
    manifest = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    size, digest = file_digest(folder / spec.file)
    entry = {"name": spec.file.removesuffix(".onnx"), "file": spec.file, "bytes": size, "sha256": digest}
    entry |= {"inputs": list(spec.inputs), "outputs": list(spec.outputs)}
    graphs = [g for g in manifest["graphs"] if g.get("file") != spec.file] + [entry]
    update_manifest(folder, {"graphs": graphs, "gate": None})  # the dense head until calibrated
    held_out = float(state.dataset.get("holdout", 0.0) or 0.0) > 0
    fit, select = run_splits(dataset, str(data), cfg, state.dataset)
    frames_ds = select if held_out else fit
    scans = [frames_ds[i][0] for i in pick_frames(len(frames_ds), frames)]
    cal = calibrate_gate(Pipeline.from_dir(folder), scans, art.threshold, recall)
    split = "selection slice" if held_out else "training"
    update_manifest(folder, {"gate": cal.gate, "gate_calibration": asdict(cal) | {"split": split}})
    return cal


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("model", type=click.Path(path_type=Path))
@click.option("--checkpoint", type=click.Path(path_type=Path), required=True, help="Its run checkpoint.")
@click.option("--dataset", required=True, help="Dataset name of --data (sim, astyx, vod).")
@click.option("--data", type=click.Path(path_type=Path), required=True, help="Dataset root.")
@click.option("--frames", default=24, show_default=True, help="Calibration frames.")
@click.option("--recall", default=RECALL, show_default=True, help="Share of the dense head's points kept.")
@one_line_errors
def main(model: Path, checkpoint: Path, dataset: str, data: Path, frames: int, recall: float) -> None:
    """Add the coarse-to-fine head (recon_head_sparse.onnx) and its calibrated gate to MODEL."""
    cal = add_sparse_head(model, checkpoint, dataset, data, frames, recall)
    click.echo(
        f"{model}: gate {cal.gate:.4f} keeps {100 * cal.points_kept:.2f} % of the dense head's points and "
        f"{100 * cal.voxels_kept:.2f} % of the half-scale voxels on {cal.frames} frames "
        f"(keep-every-point gate {cal.keep_all_gate:.4f})"
    )
