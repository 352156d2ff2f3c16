"""What one ``msdnet-bench latency`` run measures on: its models (random of a preset, or a given
folder), thresholds, the timing input and the streams of scans that the peers, the whole-frame
stream and the previous pipeline (``--before``) read."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.benchmarks.latency.config import LatencyConfig
from msdnet.benchmarks.latency.models import ModelPair, given_pair, preset_config, random_pair
from msdnet.benchmarks.latency.timing import calibrate_threshold, synthetic_radar
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.errors import MsdnetError


def _models(cfg: LatencyConfig, scratch: Path) -> ModelPair:
    if cfg.model is None:
        if cfg.r2ldm is not None:
            raise MsdnetError("--r2ldm", "only used with --model")
        base = preset_config(cfg.preset or "lite")
        if cfg.head is not None:
            base = replace(base, head_kind=cfg.head)
        if cfg.loop_steps is not None:
            base = replace(base, diffusion=replace(base.diffusion, sample_steps=cfg.loop_steps))
        return random_pair(base, scratch, cfg.seed, cfg.up_sampling)
    if cfg.against_old:
        raise MsdnetError("--against-old", "random models only (--preset): a given model has no old graphs")
    if cfg.head is not None or cfg.loop_steps is not None or cfg.up_sampling is not None:
        raise MsdnetError(
            "--head", "--head, --loop-steps and --up-sampling set up random models: not with --model"
        )
    pair = given_pair(cfg.model, cfg.r2ldm, scratch, cfg.seed)
    if cfg.preset is not None and cfg.preset != pair.cfg.preset:
        raise MsdnetError("--preset", f"{cfg.preset} differs from the model's preset {pair.cfg.preset}")
    return pair


def _target(pipe: Pipeline, cfg: LatencyConfig) -> int:
    d, h, w = pipe.artifact.grid.shape_zyx
    return max(1, min(cfg.target_points, d * h * w // 20))


def _threshold(pipe: Pipeline, weights: str, points: Any, cfg: LatencyConfig) -> tuple[float, str]:
    if weights == "random":
        thr = calibrate_threshold(pipe, points, _target(pipe, cfg), cfg.seed)
        return thr, f"random weights: threshold at the quantile leaving ~{_target(pipe, cfg)} points"
    return pipe.artifact.threshold, "manifest threshold"


def _named(points: Any, columns: tuple[str, ...]) -> Any:
    """``points`` (N, C) in MSDNet's ``columns`` as a PointCloud, so that any pipeline picks its own
    columns by name; a PointCloud as it is."""
    if isinstance(points, PointCloud):
        return points
    return PointCloud(np.ascontiguousarray(points, dtype=np.float32), tuple(columns))


def _inputs(cfg: LatencyConfig, pipe: Pipeline) -> tuple[Any, str, list]:
    """(timing input, its description, quality frames): the first --data frame, else synthetic."""
    if cfg.data is None:
        pts = synthetic_radar(pipe.columns, pipe.artifact.grid, 300, cfg.seed)
        return pts, "synthetic radar-like scan, seeded", []
    from msdnet.benchmarks.latency.quality import load_frames

    frames = load_frames(cfg.data, str(cfg.dataset), cfg.frames, pipe)
    return frames[0][1], f"{cfg.dataset} frame {frames[0][0]}", frames


def _stream(cfg: LatencyConfig, pipe: Pipeline, points: Any, frames: list) -> list:
    """The peers' stream (``peers.peer_comparison``): the timing input to warm up, then the other
    --data frames, else seeded synthetic scans of the same size (one more than the repeats)."""
    rest = [f[1] for f in frames[1:]]
    if not rest:
        rest = _seeded_scans(cfg, pipe, points, cfg.peer_repeats, 7919)  # 7919: apart from the sweeps'
    return [points, *rest]


def _seeded_scans(cfg: LatencyConfig, pipe: Pipeline, points: Any, count: int, stride: int) -> list:
    """``count`` synthetic scans of the timing input's size, seeds ``cfg.seed + stride * (k + 1)``."""
    n = len(points.points) if isinstance(points, PointCloud) else len(points)
    return [
        synthetic_radar(pipe.columns, pipe.artifact.grid, n, cfg.seed + stride * (k + 1))
        for k in range(count)
    ]


STREAM_SEED_STRIDE = 104729  # seeds of the whole-frame stream's scans: apart from the peers' and sweeps'


def _frame_stream(cfg: LatencyConfig, pipe: Pipeline, points: Any, frames: list) -> tuple[list, str]:
    """(scans, description) of the whole-frame stream (``stream_timings``): ``cfg.stream_frames``
    --data frames that no other measurement of the run reads, spread evenly and in order, else
    seeded synthetic scans of the timing input's size; none when --data has no other frame."""
    if cfg.stream_frames == 0:
        return [], "not run (--stream-frames 0)"
    if cfg.data is None:
        scans = _seeded_scans(cfg, pipe, points, cfg.stream_frames, STREAM_SEED_STRIDE)
        return scans, f"{len(scans)} seeded synthetic scans of {len(scans[0])} points"
    from msdnet.benchmarks.latency.quality import load_frames
    from msdnet.runtime.io.datasets import open_dataset

    used = {f[0] for f in frames}
    ids = [i for i in open_dataset(str(cfg.dataset), cfg.data).frame_ids if i not in used]
    if not ids:
        return [], f"not run: --data has no frame besides the {len(used)} the other measurements read"
    got = load_frames(cfg.data, str(cfg.dataset), cfg.stream_frames, pipe, frame_ids=ids)
    return [f[1] for f in got], f"{len(got)} {cfg.dataset} frames {got[0][0]} to {got[-1][0]}, in order"
