"""``msdnet-bench latency --against-old``: the same random MSDNet exported with its unoptimised graphs,
timed in the same run as the optimised ones, so that their ratio compares like with like.

The old graphs: the dense reconstruction head (no coarse-to-fine graph), the head's 2x up-sampling
as a 1x1x1 conv and an 8-D ``Transpose`` (``Up2x`` "depth_to_space", the older export
form), T_m = 50 DDIM steps, ``--provider cpu``. Against a dense or gated head, the weights
are the new model's: the same preset, seed and initialisation order (the gated head has the dense
head's layers; the step count changes no weight), so the two differ only in what the engine runs
(the ``sparse`` head kind has layers of its own, so there some weights differ). Its threshold
leaves the same number of points as the new model's (``calibrate_threshold`` to the run's target).

Both pipelines run the run's input in turn, the order swapped every repeat, so both see the same
load; the result holds each one's stage medians and ``new_over_old`` = new total / old total.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from msdnet.benchmarks.latency.models import _export
from msdnet.benchmarks.latency.timing import Scan, StageRuns, calibrate_threshold, time_stages
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.training.config import ModelConfig

OLD_STEPS = 50  # DDIM steps the unoptimised graphs run
OLD_UP = "depth_to_space"  # the head's older up-sampling export form
OLD_PROVIDER = "cpu"  # onnxruntime only, no engine picks


def old_config(cfg: ModelConfig) -> ModelConfig:
    """``cfg`` as the old graphs had it: the dense head, T_m = OLD_STEPS."""
    return dataclasses.replace(
        cfg, head_kind="dense", diffusion=dataclasses.replace(cfg.diffusion, sample_steps=OLD_STEPS)
    )


def export_old(cfg: ModelConfig, folder: Path, seed: int) -> Path:
    """The random MSDNet of ``cfg`` and ``seed`` exported into the new ``folder`` as the old graphs."""
    from msdnet.training.models.assembly import build_model

    old = old_config(cfg)
    torch.manual_seed(seed)  # as random_pair: the same weights as the new model's
    model = build_model("student", old).eval()
    _export(model, "student", old, folder, f"random init, seed {seed}; unoptimised graphs", OLD_UP)
    return folder


def old_comparison(
    new: Pipeline,
    points: Scan,
    new_threshold: float,
    cfg: ModelConfig,
    scratch: Path,
    threads: int,
    target: int,
    repeats: int,
    seed: int = 0,
) -> dict[str, Any]:
    """Time ``new`` (already warm, its gate set) against the old graphs of the same random model
    (module docstring) on ``points``; -> both runs' stage medians and ``new_over_old``."""
    old = Pipeline.from_dir(export_old(cfg, scratch / "old-graphs", seed), OLD_PROVIDER, threads)
    old.warmup()
    old.gate = None  # the dense head
    old_threshold = calibrate_threshold(old, points, target, seed)
    runs = {"old": StageRuns({}), "new": StageRuns({})}
    args = {"old": (old, old_threshold), "new": (new, new_threshold)}
    for r in tqdm(range(repeats), desc="old graphs vs new", unit="pair", disable=None):
        for key in ("old", "new") if r % 2 == 0 else ("new", "old"):
            pipe, thr = args[key]
            runs[key].add(time_stages(pipe, points, None, thr, 1, seed))
    out: dict[str, Any] = {"repeats": repeats}
    for key, acc in runs.items():
        pipe, thr = args[key]
        stages = {k: v["median"] for k, v in acc.summaries().items()}
        out[key] = {
            "stages_ms": stages,
            "total_ms": stages["total"],
            "steps": pipe.artifact.diffusion.sample_steps,
            "head": "dense" if pipe.gate is None else f"coarse-to-fine, gate {pipe.gate:.4g}",
            "provider": pipe.provider,
            "threshold": thr,
            "decoded": acc.decoded,
        }
    out["old"] |= {"up_sampling": OLD_UP}
    out["new_over_old"] = out["new"]["total_ms"] / out["old"]["total_ms"]
    pairs = np.asarray(runs["new"].seconds["total"]) / np.asarray(runs["old"].seconds["total"])
    out["new_over_old_per_pair"] = [float(x) for x in pairs]  # each repeat's ratio, same load
    return out
