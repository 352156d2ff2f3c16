"""Downstream tasks over simulator sequences: GICP odometry and ScanContext place recognition.

A simulated folder (``msdnet-data simulate``) holds the VoD layout plus ``sequences.json`` (frame
ids per sequence, loop closures). Every frame of the chosen sequences is preprocessed on the
models' grid; each method (raw radar, every model, and the LiDAR reference: the preprocessed
LiDAR, grid box + field of view, ground removed — the cloud the models learn to produce) gives
one cloud per frame, cropped to the grid box and field of view. "LiDAR (full sweep)" (the whole
sweep, downsampled to 0.25 m voxels) checks the harness itself: its errors must be near zero.
The true poses (``Frame.pose``, radar frame -> odom) give the ground truth.

- Odometry: scan-to-scan GICP (``benchmarks.downstream.odometry.gicp_odometry``, small_gicp) per sequence;
  relative translation / rotation errors over all consecutive pairs of all sequences.
- Place recognition: ScanContext Recall@K (``benchmarks.downstream.place.recall_at_k``) per sequence;
  pooled over sequences by query count.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import small_gicp
from tqdm import tqdm

from msdnet.benchmarks.downstream.odometry import (
    GicpSettings,
    gicp_odometry,
    relative_errors,
    relative_from_poses,
)
from msdnet.benchmarks.downstream.place import ScanContextConfig, recall_at_k
from msdnet.benchmarks.eval_methods import Method
from msdnet.benchmarks.quality.suite import grid_dict
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.datasets import FrameDataset
from msdnet.runtime.io.datasets.frame import read_json
from msdnet.runtime.io.datasets.preprocess import preprocess_frame
from msdnet.runtime.metrics.crop import crop_to_grid
from msdnet.runtime.spec.grid import GridConfig

SEQUENCES_FILE = "sequences.json"
LIDAR_NAME = "LiDAR"  # the reference cloud, always evaluated
FULL_LIDAR_NAME = "LiDAR (full sweep)"  # the whole sweep: checks the harness (near-zero errors)
FULL_SWEEP_VOXEL = 0.25  # m: voxel-grid downsampling of the full sweep (GICP's own resolution)


@dataclass(frozen=True)
class SimSequence:
    """One simulated drive."""

    index: int  # position in sequences.json
    frame_ids: tuple[str, ...]  # frames in time order (10 Hz)
    has_loop: bool  # whether the drive revisits a place (loop closures listed)


def read_sequences(root: Path) -> list[SimSequence]:
    """The sequences of a simulated folder; MsdnetError when sequences.json is missing or broken."""
    path = Path(root) / SEQUENCES_FILE
    if not path.is_file():
        raise MsdnetError(path, "not found: --data must be a simulated folder (msdnet-data simulate)")
    doc = read_json(path)
    entries = doc.get("sequences") if isinstance(doc, dict) else None
    if not isinstance(entries, list) or not entries:
        raise MsdnetError(path, "no 'sequences' list")
    out = []
    for i, e in enumerate(entries):
        ids = e.get("frame_ids") if isinstance(e, dict) else None
        if not isinstance(ids, list) or not all(isinstance(f, str) for f in ids):
            raise MsdnetError(path, f"sequence {i} has no 'frame_ids' list of strings")
        out.append(SimSequence(i, tuple(ids), bool(e.get("has_loop", False))))
    return out


def select_sequences(
    sequences: list[SimSequence], indices: tuple[int, ...] | None, max_frames: int | None
) -> list[SimSequence]:
    """The sequences numbered ``indices`` (all when None), each cut to its first ``max_frames``."""
    if indices is not None:
        bad = [i for i in indices if not 0 <= i < len(sequences)]
        if bad:
            raise MsdnetError("--sequences", f"no sequence {bad[0]} (have 0..{len(sequences) - 1})")
        sequences = [sequences[i] for i in indices]
    if max_frames is not None:
        sequences = [SimSequence(s.index, s.frame_ids[:max_frames], s.has_loop) for s in sequences]
    return sequences


def full_sweep(xyz: np.ndarray) -> np.ndarray:
    """xyz: (N, 3) the whole LiDAR sweep, radar frame -> (M, 3) float32 voxel-grid downsampled
    (``FULL_SWEEP_VOXEL``, small_gicp's sampler) to keep long sequences in memory."""
    sampled = small_gicp.voxelgrid_sampling(np.ascontiguousarray(xyz, dtype=np.float64), FULL_SWEEP_VOXEL)
    return np.ascontiguousarray(sampled.points()[:, :3], dtype=np.float32)  # (M, 4) homogeneous -> xyz


@dataclass
class SequenceClouds:
    """Every method's cloud for every frame of the chosen sequences, with the true poses."""

    sequences: list[SimSequence]  # the sequences, in order
    poses: list[list[np.ndarray]]  # per sequence, per frame: (4, 4) float64 radar -> odom
    clouds: dict[str, list[list[np.ndarray]]]  # method name -> sequence -> frame -> (M, 3) float32


def run_sequences(
    ds: FrameDataset,
    sequences: list[SimSequence],
    methods: list[Method],
    grid: GridConfig,
    seed: int = 0,
    progress: bool = True,
) -> SequenceClouds:
    """Run every method (plus the LiDAR reference) on every frame; see the module docstring."""
    names = [m.name for m in methods] + [LIDAR_NAME, FULL_LIDAR_NAME]
    sc = SequenceClouds(sequences, [], {n: [] for n in names})
    bar = tqdm(
        total=sum(len(s.frame_ids) for s in sequences),
        desc="frames",
        unit="frame",
        disable=not progress or None,
    )
    for seq in sequences:
        poses: list[np.ndarray] = []
        per_method: dict[str, list[np.ndarray]] = {n: [] for n in names}
        for fid in seq.frame_ids:
            raw = ds.get(fid)
            frame = preprocess_frame(raw, grid)
            if frame.pose is None:
                raise MsdnetError(ds.root, f"frame {fid} has no pose; odometry and place need poses")
            poses.append(frame.pose)
            for m in methods:
                per_method[m.name].append(crop_to_grid(m.run(frame.radar, seed), grid))
            per_method[LIDAR_NAME].append(crop_to_grid(frame.lidar.xyz, grid))
            per_method[FULL_LIDAR_NAME].append(full_sweep(raw.lidar.xyz))
            bar.update(1)
        sc.poses.append(poses)
        for n in names:
            sc.clouds[n].append(per_method[n])
    bar.close()
    return sc


def _errors_row(est: list[np.ndarray], gt: list[np.ndarray]) -> dict[str, Any]:
    if not gt:
        return {
            "translation_m": float("nan"),
            "rotation_deg": float("nan"),
            "translation_pct": float("nan"),
            "pairs": 0,
        }
    e = relative_errors(est, gt)
    return {
        "translation_m": e.translation_m,
        "rotation_deg": e.rotation_deg,
        "translation_pct": e.translation_pct,
        "pairs": e.pairs,
    }


def odometry_results(
    sc: SequenceClouds, settings: GicpSettings | None = None, progress: bool = True
) -> dict[str, Any]:
    """Per method: relative errors over all frame pairs (``overall``) and per sequence."""
    settings = settings or GicpSettings()
    truth = [relative_from_poses(p) for p in sc.poses]
    out: dict[str, Any] = {}
    for name in tqdm(list(sc.clouds), desc="odometry", unit="method", disable=not progress or None):
        est = [gicp_odometry(clouds, settings) for clouds in sc.clouds[name]]
        per_seq = {str(s.index): _errors_row(e, t) for s, e, t in zip(sc.sequences, est, truth, strict=True)}
        flat_est = [t for e in est for t in e]
        flat_gt = [t for g in truth for t in g]
        out[name] = {"overall": _errors_row(flat_est, flat_gt), "sequences": per_seq}
    return out


def place_results(
    sc: SequenceClouds,
    ks: tuple[int, ...] = (1, 3, 5),
    revisit_radius: float = 5.0,
    exclude_recent: int = 50,
    cfg: ScanContextConfig | None = None,
) -> dict[str, Any]:
    """Per method: Recall@K pooled over sequences (weighted by queries) and per sequence."""
    out: dict[str, Any] = {}
    for name, per_seq_clouds in sc.clouds.items():
        hits = dict.fromkeys(ks, 0.0)
        queries = 0
        per_seq = {}
        for seq, clouds, poses in zip(sc.sequences, per_seq_clouds, sc.poses, strict=True):
            positions = np.stack([p[:3, 3] for p in poses])  # (F, 3) metres, odom frame
            r = recall_at_k(clouds, positions, ks, revisit_radius, exclude_recent, cfg)
            per_seq[str(seq.index)] = {
                "recall": {str(k): v for k, v in r.recall.items()},
                "queries": r.queries,
            }
            queries += r.queries
            for k in ks:
                hits[k] += r.recall[k] * r.queries if r.queries else 0.0
        recall = {str(k): hits[k] / queries if queries else float("nan") for k in ks}
        out[name] = {"overall": {"recall": recall, "queries": queries}, "sequences": per_seq}
    return out


def run_downstream(
    task: str,
    ds: FrameDataset,
    sequences: list[SimSequence],
    methods: list[Method],
    grid: GridConfig,
    out: Path,
    evaluation: dict[str, Any],
    place_options: dict[str, Any] | None = None,
    seed: int = 0,
    progress: bool = True,
) -> dict[str, Any]:
    """``task`` "odometry" or "place": run, then write ``out/results.json`` and ``out/results.md``.

    ``place_options``: keyword arguments of :func:`place_results` (ks, revisit_radius,
    exclude_recent). Returns results.json's content.
    """
    from msdnet.benchmarks.downstream.report import odometry_markdown, place_markdown
    from msdnet.benchmarks.machine import machine_info
    from msdnet.benchmarks.quality.report import write_json, write_text

    sc = run_sequences(ds, sequences, methods, grid, seed, progress)
    if task == "odometry":
        settings = GicpSettings()
        results = odometry_results(sc, settings, progress)
        task_info: dict[str, Any] = {"gicp": settings.__dict__}
    elif task == "place":
        opts = place_options or {}
        results = place_results(sc, **opts)
        task_info = {**opts, "scan_context": ScanContextConfig().__dict__}
    else:
        raise ValueError(f"task must be odometry or place, got {task!r}")
    lidar = [
        {"name": LIDAR_NAME, "role": "lidar", "kind": "lidar", "backend": "input", "source": "reference"},
        {
            "name": FULL_LIDAR_NAME,
            "role": "lidar",
            "kind": "lidar",
            "backend": "input",
            "source": "full sweep",
        },
    ]
    doc = {
        "evaluation": {
            **evaluation,
            "task": task,
            "sequences": [
                {"index": s.index, "frames": len(s.frame_ids), "has_loop": s.has_loop} for s in sequences
            ],
            "seed": seed,
            "clouds": "each method's output and the preprocessed LiDAR, cropped to the grid box + FOV",
            "grid": grid_dict(grid),
            **task_info,
        },
        "machine": machine_info(sgemm=False).to_json(),
        "methods": [m.describe() for m in methods] + lidar,
        "results": results,
    }
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "results.json", doc)
    markdown = odometry_markdown(doc) if task == "odometry" else place_markdown(doc)
    write_text(out / "results.md", markdown)
    return doc
