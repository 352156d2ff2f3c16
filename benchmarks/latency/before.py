"""``msdnet-bench latency --before MODEL_DIR``: the previous pipeline (an exported model folder,
e.g. a copy of the shipped model) against the new one, in the same run, on the same scans.

Both pipelines are loaded fresh at the run's provider (by default ``auto``, the default of
``msdnet-infer``), so neither has seen a scan before it is timed on it: OpenVINO prepares kernels
per input shape, and the run's other measurements have shown the new pipeline's own sessions the
timing input and the stream. Both are warmed up on the timing input, then each scan of the stream
runs through both, one after the other, the order swapped every scan, so both see the same load.
A given model decodes as its manifest says (threshold or range thresholds, keep rule), the previous
one as its own; against a random new model, the new keeps the run's gate and threshold and the
previous one gets a threshold leaving the same number of points, as ``--against-old`` does.

The result holds each pipeline's stage medians and the ratios the speed goals name:
``frame_over_before`` (whole frame, new median / previous median) and ``encoder_over_before``
(the encoder stage alone), with the per-scan ratios beside them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msdnet.benchmarks.latency.timing import Scan, StageRuns, calibrate_threshold, time_stages
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.errors import MsdnetError

RATIO_STAGES = {"frame_over_before": "total", "encoder_over_before": "encoder"}  # ratio key -> stage
FRAME_GOALS = {"lite": 0.7, "paper": 0.6, "paper-width": 0.6}  # whole frame, new / previous, by preset
ENCODER_GOALS = {"paper-width": 0.5}  # the encoder alone, new / previous, by preset


def load_before(folder: Path, provider: str, threads: int | None) -> Pipeline:
    """The previous pipeline: an MSDNet (student) folder at ``provider``, warmed up."""
    if not (folder / "manifest.json").is_file():
        raise MsdnetError("--before", f"{folder} is not an exported model folder (no manifest.json)")
    pipe = Pipeline.from_dir(folder, provider, threads)
    if pipe.kind != "student":
        raise MsdnetError("--before", f"{folder} holds a {pipe.kind} model, expected student (MSDNet)")
    pipe.warmup()
    return pipe


def _engines(pipe: Pipeline) -> dict[str, str]:
    """Graph file -> the engine it runs on: onnxruntime, openvino or openvino-bf16."""
    if pipe.auto is not None:
        return {f: p.engine for f, p in pipe.auto.picks.items()}
    names = {None: "onnxruntime", "f32": "openvino", "bf16": "openvino-bf16"}  # OpenVinoSession.precision
    return {f: names[getattr(s, "precision", None)] for f, s in pipe.sessions.items()}


def _described(pipe: Pipeline, acc: StageRuns, threshold: float | None) -> dict[str, Any]:
    stages = {k: v["median"] for k, v in acc.summaries().items()}
    return {
        "folder": str(pipe.artifact.root),
        "stages_ms": stages,
        "total_ms": stages["total"],
        "encoder_ms": stages["encoder"],
        "steps": pipe.artifact.diffusion.sample_steps,
        "head": "dense" if pipe.gate is None else f"coarse-to-fine, gate {pipe.gate:.4g}",
        "encoder_form": pipe.artifact.manifest.get("encoder_form", "rulebook"),
        "provider": pipe.provider,
        "engines": _engines(pipe),
        "threshold": pipe.artifact.threshold if threshold is None else threshold,
        "threshold_note": "given" if threshold is not None else "the manifest's rules",
        "range_thresholds": None
        if threshold is not None or pipe.range_thresholds is None
        else pipe.range_thresholds.to_json(),
        "keep_radar_threshold": pipe.keep_threshold if threshold is None else None,
        "decoded": acc.decoded,
    }


def before_comparison(
    new: Pipeline,
    before: Pipeline,
    warm: Scan,
    scans: list[Scan],
    thresholds: tuple[float | None, float | None],
    source: str,
    seed: int = 0,
) -> dict[str, Any]:
    """Time ``new`` against ``before`` (both fresh and warm, gates set) on ``scans``, each scan once
    through each, in alternating order (module docstring); ``warm`` (the timing input) first, once
    each, untimed. ``thresholds``: (new, before); None decodes as the model's manifest says
    (its threshold or range thresholds, and its keep rule), as ``msdnet-infer`` does. Scans are
    named point clouds or arrays in the new model's columns. -> both pipelines' stage medians, the
    ratios of ``RATIO_STAGES`` and per scan."""
    if not scans:
        raise ValueError("before_comparison needs at least one scan")
    pipes = {"new": (new, thresholds[0]), "before": (before, thresholds[1])}
    for pipe, thr in pipes.values():
        pipe(_for(pipe, new, warm), threshold=thr, seed=seed)
    runs = {"new": StageRuns({}), "before": StageRuns({})}
    for k, scan in enumerate(tqdm(scans, desc="new vs the previous pipeline", unit="scan", disable=None)):
        for key in ("new", "before") if k % 2 == 0 else ("before", "new"):
            pipe, thr = pipes[key]
            runs[key].add(time_stages(pipe, _for(pipe, new, scan), None, thr, 1, seed))
    out: dict[str, Any] = {"scans": len(scans), "source": source}
    for key, (pipe, thr) in pipes.items():
        out[key] = _described(pipe, runs[key], thr)
    for ratio, stage in RATIO_STAGES.items():
        out[ratio] = out["new"]["stages_ms"][stage] / out["before"]["stages_ms"][stage]
        per = np.asarray(runs["new"].seconds[stage]) / np.asarray(runs["before"].seconds[stage])
        out[f"{ratio}_per_scan"] = [float(x) for x in per]  # each scan's ratio, same load
        out[f"{ratio}_paired_median"] = float(np.median(per))
    return out


def _for(pipe: Pipeline, new: Pipeline, scan: Scan) -> Scan:
    """``scan`` for ``pipe``: as it is for the new pipeline; for the previous one, by column name
    (it may read other columns than the new model)."""
    if pipe is new or isinstance(scan, PointCloud):
        return scan
    return PointCloud(np.ascontiguousarray(scan, dtype=np.float32), tuple(new.columns))


def before_threshold(
    before: Pipeline, weights: str, warm: Scan, new: Pipeline, target: int, seed: int = 0
) -> float:
    """The previous pipeline's threshold: its manifest's, or against a random new model one that
    leaves the run's ``target`` number of points on the timing input (``calibrate_threshold``)."""
    if weights != "random":
        return before.artifact.threshold
    return calibrate_threshold(before, _for(before, new, warm), target, seed)


def before_section(res: dict[str, Any]) -> list[str]:
    """results.md: the new pipeline against the previous one, per stage, and the ratios."""
    b = res.get("before") or {}
    if "new" not in b:
        return []
    n, p = b["new"], b["before"]
    out = ["", "## Against the previous pipeline (--before)", ""]
    out.append(
        f"Previous: `{p['folder']}` ({p['steps']} steps, {p['head']} head, {p['encoder_form']} encoder, "
        f"provider {p['provider']}); new: {n['steps']} steps, {n['head']} head, {n['encoder_form']} "
        f"encoder, provider {n['provider']}. Both loaded fresh and run on the same {b['scans']} scans "
        f"({b['source']}), each scan once through each, the order swapped every scan."
    )
    out += ["", "| stage | new median ms | previous median ms | new / previous |", "|---|---:|---:|---:|"]
    for stage, ms in n["stages_ms"].items():
        old = p["stages_ms"][stage]
        ratio = ms / old if old > 0 else float("nan")
        out.append(f"| {stage} | {ms:.2f} | {old:.2f} | {ratio:.3f} |")
    out += [
        "",
        f"Whole frame, new / previous (`frame_over_before`): **{b['frame_over_before']:.3f}** (median of "
        f"the per-scan ratios {b['frame_over_before_paired_median']:.3f}); encoder "
        f"(`encoder_over_before`): **{b['encoder_over_before']:.3f}** "
        f"({b['encoder_over_before_paired_median']:.3f}). Decoded points: {n['decoded']} new, "
        f"{p['decoded']} previous (last scan).",
    ]
    cells = _engine_cells(n["engines"], p["engines"])
    out += ["", "Engines per graph (new / previous): " + ("; ".join(cells) or "onnxruntime throughout") + "."]
    return out


def _engine_cells(new: dict[str, str], old: dict[str, str]) -> list[str]:
    """``graph new / previous`` for each graph that is not on onnxruntime in both pipelines."""
    files = list(dict.fromkeys([*new, *old]))
    both = {f: (new.get(f, "-"), old.get(f, "-")) for f in files}
    return [f"{f} {a} / {b}" for f, (a, b) in both.items() if (a, b) != ("onnxruntime", "onnxruntime")]


def before_goal_rows(res: dict[str, Any]) -> list[tuple[str, float, str, float]]:
    """(goal, measured, op, target) rows of the speed goals against the previous pipeline."""
    b, preset = res.get("before") or {}, res["preset"]
    if "new" not in b:
        return []
    rows = []
    if preset in FRAME_GOALS:
        frame = ("whole frame / the previous pipeline's", b["frame_over_before"], "<=", FRAME_GOALS[preset])
        rows.append(frame)
    if preset in ENCODER_GOALS:
        enc = ("encoder / the previous pipeline's", b["encoder_over_before"], "<=", ENCODER_GOALS[preset])
        rows.append(enc)
    return rows
