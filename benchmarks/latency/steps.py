"""``msdnet-bench steps``: MSDNet Table III on a dataset split, the step-count sweep on its own.

The quality half of ``msdnet-bench latency``'s Table III (``latency.quality.quality_by_steps``)
for one exported model on every frame of a split (or ``--max-frames`` of them, spread evenly):
per T_m the mean CD, MHD, F-scores, JSD and MMD against the preprocessed LiDAR (scored as
``msdnet-bench quality`` scores them) and the median ms per frame of those same calls, T_m
round-robin per frame so that load from other processes hits every step count alike. Each
metric is also given relative to the largest T_m of the sweep, the figure the paper quotes
(T_m = 10 within 3.5 % of T_m = 50 on CD). Writes ``--out/results.json`` and ``results.md``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, cast

import click

from msdnet.benchmarks.eval_cli import SPLITS, int_tuple
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import checks_outputs
from msdnet.runtime.io.datasets import DATASET_NAMES

DEFAULT_STEPS = "1,2,4,10,25,50"
CLOSE_PCT = 1.0  # "within 1 % of the largest T_m" (the few-step goal)
PCT_KEYS = ("cd", "mhd", "fscore@0.5", "jsd")  # metrics also shown relative to the largest T_m
LOWER_IS_BETTER = {"cd": True, "mhd": True, "fscore@0.5": False, "jsd": True}


def relative_pct(value: float, ref: float) -> float:
    """100 (value - ref) / |ref|; nan when either is not finite or ref is 0."""
    if not (math.isfinite(value) and math.isfinite(ref)) or ref == 0:
        return float("nan")
    return 100.0 * (value - ref) / abs(ref)


def fewest_close_steps(rows: list[dict[str, Any]]) -> int | None:
    """The smallest T_m whose CD and F@0.5 are both within ``CLOSE_PCT`` of the largest T_m's
    (no worse than that, or better), None when none is."""
    for row in sorted(rows, key=lambda r: r["steps"]):
        cd, f = row["vs_last_pct"]["cd"], row["vs_last_pct"]["fscore@0.5"]
        if math.isfinite(cd) and math.isfinite(f) and cd <= CLOSE_PCT and f >= -CLOSE_PCT:
            return int(row["steps"])
    return None


def steps_markdown(doc: dict[str, Any]) -> str:
    """results.md of one sweep."""
    from msdnet.benchmarks.latency.report import PAPER_TABLE3

    ev, m, rows = doc["evaluation"], doc["machine"], doc["rows"]
    last = rows[-1]["steps"]
    load = f"{m['loadavg_start'][0]:.1f} at the start, {m['loadavg_end'][0]:.1f} at the end"
    out = [
        f"# Quality and time against the DDIM steps T_m: `{ev['model']}` on {ev['dataset']} / "
        f"{ev['split']}, {ev['frames']} frames",
        "",
        f"Command: `{doc['command']}`",
        "",
        f"Machine: {m['cpu']} ({m['logical_cores']} logical cores), {doc['threads']} threads, provider "
        f"`{doc['provider']}`; load average {load}"
        + (
            " (the machine was shared with other work, so the ms are upper bounds)"
            if max(m["loadavg_start"][0], m["loadavg_end"][0]) > m["logical_cores"] * 0.75
            else ""
        )
        + ". The ms ratios come from one run (T_m round-robin per frame). Threshold "
        f"{doc['threshold']:.4g} ({doc['threshold_note']}"
        + (f"; by range {doc['range_thresholds']}" if doc.get("range_thresholds") else "")
        + f"), seed {ev['seed']}, gate {doc['gate']}.",
        "",
        f"Scored like `msdnet-bench quality`: prediction and LiDAR cropped to the grid box and the "
        f"field of view, mean over the frames; Δ columns are relative to T_m = {last}.",
        "",
        "| T_m | CD m | Δ CD | MHD m | Δ MHD | F@0.5 m | Δ F@0.5 | JSD | Δ JSD | F@0.2 m | MMD (×10⁻⁴) "
        "| points | ms / frame | p90 | DDIM loop ms | paper CD |",
        "|---:|" + "---:|" * 14 + "---:|",
    ]
    for r in rows:
        d = r["vs_last_pct"]
        paper = PAPER_TABLE3.get(r["steps"], (None,))[0]
        out.append(
            f"| {r['steps']} | {r['cd']:.3f} | {d['cd']:+.1f} % | {r['mhd']:.3f} | {d['mhd']:+.1f} % | "
            f"{r['fscore@0.5']:.3f} | {d['fscore@0.5']:+.1f} % | {r['jsd']:.3f} | {d['jsd']:+.1f} % | "
            f"{r['fscore@0.2']:.3f} | {r['mmd'] * 1e4:.1f} | {r['points']:.0f} | {r['ms']:.1f} | "
            f"{r['ms_p90']:.1f} | {r['loop_ms']:.1f} | {'–' if paper is None else paper} |"
        )
    few = doc["fewest_steps_within_1pct"]
    out += [
        "",
        f"Fewest T_m within {CLOSE_PCT:g} % of T_m = {last} on both CD and F@0.5: "
        + (f"**{few}**." if few is not None else "none of the sweep."),
        "",
        "Paper (MSDNet Table III, VoD, RTX 4090; CD variant and unit not stated): compare the trend "
        "over T_m, not the values.",
    ]
    return "\n".join(out) + "\n"


def run_steps(
    model: Path,
    dataset: str,
    data: Path,
    split: str,
    steps: tuple[int, ...],
    out: Path,
    max_frames: int | None = None,
    threshold: float | None = None,
    threads: int | None = None,
    provider: str = "cpu",
    seed: int = 0,
    command: str = "",
    checkpoint: Path | None = None,
) -> dict[str, Any]:
    """Run the sweep (module docstring), write ``out/results.json`` and ``results.md``; -> the JSON.
    ``split`` "select": the held-out selection slice of the training run of ``checkpoint`` (default:
    the manifest's ``source``), where T_m may be chosen (never on validation)."""
    from msdnet.benchmarks.latency.quality import load_frames, quality_by_steps
    from msdnet.benchmarks.machine import machine_info
    from msdnet.benchmarks.quality.report import write_json, write_text
    from msdnet.runtime.engine.pipeline import Pipeline

    load_start = os.getloadavg()
    pipe = Pipeline.from_dir(model, provider=provider, threads=threads)
    if pipe.kind != "student":
        raise MsdnetError(model, f"a {pipe.kind} model: the T_m sweep is MSDNet's (Table III)")
    steps = tuple(sorted(set(steps)))
    try:
        for s in steps:
            pipe.coefficients(s)
    except MsdnetError as err:
        raise MsdnetError("--steps", str(err).split(": ", 1)[-1]) from None
    pipe.warmup()
    ids = None
    if split == "select":
        from msdnet.benchmarks.stages import split_frames
        from msdnet.training.recipe.checkpoint import read_checkpoint

        source = checkpoint or pipe.artifact.manifest.get("source")
        if not source:
            raise MsdnetError("--split", "select needs --checkpoint (the manifest names no source run)")
        run_dataset = read_checkpoint(Path(source))[2].dataset
        ids = split_frames(run_dataset, dataset, data, "select", max_frames)[1]
    frames = load_frames(data, dataset, max_frames, pipe, None if split in ("all", "select") else split, ids)
    thr = pipe.artifact.threshold if threshold is None else threshold
    bands = pipe.range_thresholds if threshold is None else None  # the manifest's, as the runtime
    rows = quality_by_steps(pipe, frames, steps, threshold, seed)
    for r in rows:
        r["vs_last_pct"] = {k: relative_pct(r[k], rows[-1][k]) for k in PCT_KEYS}
    doc = {
        "command": command,
        "evaluation": {
            "model": str(model),
            "dataset": dataset,
            "data": str(data),
            "split": split,
            "frames": len(frames),
            "frame_ids": [f[0] for f in frames],
            "seed": seed,
            "reference": "preprocessed LiDAR (grid box + field of view, ground removed)",
        },
        "machine": {
            **machine_info(sgemm=False).to_json(),
            "loadavg_start": list(load_start),
            "loadavg_end": list(os.getloadavg()),
        },
        "provider": provider,
        "provider_auto": None if pipe.auto is None else pipe.auto.to_json(),
        "threads": threads or os.cpu_count(),
        "threshold": thr,
        "threshold_note": "manifest" if threshold is None else "--threshold",
        "range_thresholds": None if bands is None else bands.to_json(),
        "gate": pipe.gate,
        "manifest_steps": pipe.artifact.diffusion.sample_steps,
        "rows": rows,
        "fewest_steps_within_1pct": fewest_close_steps(rows),
    }
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "results.json", doc)
    write_text(out / "results.md", steps_markdown(doc))
    return doc


@click.command("steps", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--model", required=True, type=click.Path(path_type=Path), help="Exported MSDNet folder.")
@click.option("--dataset", required=True, type=click.Choice(DATASET_NAMES), help="Layout of --data.")
@click.option("--data", required=True, type=click.Path(path_type=Path), help="Dataset root.")
@click.option(
    "--split",
    type=click.Choice([*SPLITS, "select"]),
    default="val",
    show_default=True,
    help="Frames scored; select = the run's held-out selection slice (choose T_m there).",
)
@click.option(
    "--checkpoint",
    type=click.Path(path_type=Path),
    help="--split select: the training run's checkpoint [the manifest's source].",
)
@click.option("--steps", "steps_text", default=DEFAULT_STEPS, show_default=True, help="T_m values.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Folder for results.*")
@click.option("--max-frames", type=click.IntRange(min=1), help="Score this many frames, spread evenly.")
@click.option("--threshold", type=click.FloatRange(0, 1, min_open=True, max_open=True), help="Occupancy.")
@click.option("--threads", type=click.IntRange(min=1), help="Intra-op threads [all cores].")
@click.option(
    "--provider",
    default="cpu",
    show_default=True,
    help="cpu, cpu-shared, auto, auto-bf16, openvino, openvino-bf16, cuda or tensorrt.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Diffusion noise seed.")
@one_line_errors
@checks_outputs(out="into")  # before any work
def steps_command(steps_text: str, **opts: Any) -> None:
    """CD, MHD, F-scores, JSD and ms per frame against the DDIM steps T_m on a dataset split."""
    from msdnet.runtime.providers.session import resolve_providers

    resolve_providers(opts["provider"])
    steps = cast(tuple[int, ...], int_tuple("--steps", steps_text, 1))
    command = (
        f"msdnet-bench steps --model {opts['model']} --dataset {opts['dataset']} --data {opts['data']} "
        f"--split {opts['split']} --steps {','.join(map(str, steps))} --out {opts['out']}"
    )
    for flag in ("max_frames", "threshold", "threads", "checkpoint"):
        if opts[flag] is not None:
            command += f" --{flag.replace('_', '-')} {opts[flag]}"
    command += "" if opts["provider"] == "cpu" else f" --provider {opts['provider']}"
    command += "" if opts["seed"] == 0 else f" --seed {opts['seed']}"
    doc = run_steps(steps=steps, command=command, **opts)
    for r in doc["rows"]:
        click.echo(
            f"T_m {r['steps']:>3}: CD {r['cd']:.3f} m ({r['vs_last_pct']['cd']:+.1f} %), "
            f"MHD {r['mhd']:.3f} m, "
            f"F@0.5 {r['fscore@0.5']:.3f}, JSD {r['jsd']:.3f}, {r['ms']:.1f} ms/frame"
        )
    click.echo(f"wrote {opts['out'] / 'results.json'} and {opts['out'] / 'results.md'}")
