"""``msdnet-bench quality | odometry | place``: the evaluation commands.

- ``quality``: raw radar, every ``--model`` (artifact folder, onnxruntime), every
  ``--checkpoint`` (torch) and every ``--ablation NAME=DIR`` scored on the same frames of a
  dataset split against the preprocessed LiDAR (``benchmarks.quality.suite``).
- ``odometry`` / ``place``: the same methods plus LiDAR over simulated sequences
  (``benchmarks.downstream.suite``).

Each writes ``--out/results.json`` and ``--out/results.md``; bad input exits 2 with one line.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import checks_outputs
from msdnet.runtime.io.datasets import DATASET_NAMES
from msdnet.runtime.spec.grid import GRID_PRESETS, GridConfig

if TYPE_CHECKING:
    from msdnet.benchmarks.eval_methods import Method

SPLITS = ("train", "val", "test", "all")  # "all": every frame of the folder
PathType = click.Path(path_type=Path)


def int_tuple(option: str, text: str | None, minimum: int) -> tuple[int, ...] | None:
    """ "0,2" -> (0, 2); MsdnetError naming ``option`` on anything else."""
    if text is None:
        return None
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise MsdnetError(option, f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < minimum:
        raise MsdnetError(option, f"expected integers >= {minimum}, got {text!r}")
    return values


def model_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Options shared by the three commands: models, inference settings, output."""
    options = [
        click.option("--out", required=True, type=PathType, help="Folder for results.json / results.md."),
        click.option(
            "--model", "models", multiple=True, type=PathType, help="Exported model folder (repeat)."
        ),
        click.option(
            "--checkpoint", "checkpoints", multiple=True, type=PathType, help="Checkpoint run in torch."
        ),
        click.option("--steps", type=click.IntRange(min=1), help="MSDNet DDIM steps [model default]."),
        click.option("--r2ldm-steps", type=click.IntRange(min=1), help="R2LDM DDIM steps [model default]."),
        click.option(
            "--threshold", type=click.FloatRange(0, 1, min_open=True, max_open=True), help="Occupancy."
        ),
        click.option("--threads", type=click.IntRange(min=1), help="onnxruntime / torch threads."),
        click.option("--provider", default="cpu", show_default=True, help="cpu, cuda or tensorrt."),
        click.option("--grid", type=click.Choice(sorted(GRID_PRESETS)), help="Grid without models [lite]."),
        click.option("--seed", type=int, default=0, show_default=True, help="Diffusion noise seed."),
    ]
    for option in reversed(options):
        func = option(func)
    return func


def _methods(
    opts: dict[str, Any], ablations: tuple[str, ...] = (), keep_radar: bool = False
) -> tuple[list[Method], GridConfig]:
    """(methods, grid) from the shared options."""
    from msdnet.benchmarks.eval_methods import RunSettings, build_methods, common_grid

    settings = RunSettings(
        opts["steps"], opts["r2ldm_steps"], opts["threshold"], opts["threads"], opts["provider"]
    )
    methods = build_methods(
        list(opts["models"]), list(opts["checkpoints"]), list(ablations), settings, keep_radar
    )
    return methods, common_grid(methods, opts["grid"])


@click.command("quality", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--dataset", required=True, type=click.Choice(DATASET_NAMES), help="Layout of --data.")
@click.option("--data", required=True, type=PathType, help="Dataset root.")
@click.option("--split", type=click.Choice(SPLITS), default="val", show_default=True, help="Frames scored.")
@click.option("--ablation", "ablations", multiple=True, help="NAME=DIR: ablation model (repeat).")
@click.option(
    "--keep-radar", is_flag=True, help="Also score each MSDNet model's output joined with the input radar."
)
@click.option("--max-frames", type=click.IntRange(min=1), help="Score this many frames, spread evenly.")
@click.option("--pictures", type=click.IntRange(min=0), default=3, show_default=True, help="BEV strips.")
@click.option("--save", type=PathType, help="Also write every cloud: DIR/<method>/<frame>.npy.")
@click.option(
    "--metrics",
    type=click.Choice(("ours", "official", "both")),
    default="ours",
    show_default=True,
    help="Metric formulas: ours, the R2LDM authors' evaluation script's (official), or both.",
)
@model_options
@one_line_errors
@checks_outputs(out="into", save="into")  # before any work
def quality_command(**opts: Any) -> None:
    """Quality against the LiDAR of raw radar, R2LDM, MSDNet (torch / onnxruntime) and ablations:
    scene and object metrics per frame and their means."""
    from msdnet.benchmarks.quality.suite import run_quality
    from msdnet.runtime.io.datasets import open_dataset

    methods, grid = _methods(opts, opts["ablations"], opts["keep_radar"])
    split = None if opts["split"] == "all" else opts["split"]
    ds = open_dataset(opts["dataset"], opts["data"], split)
    evaluation = {"dataset": opts["dataset"], "data": str(opts["data"]), "split": opts["split"]}
    doc = run_quality(
        ds,
        evaluation,
        methods,
        grid,
        opts["out"],
        opts["max_frames"],
        opts["seed"],
        opts["pictures"],
        opts["save"],
        metrics=opts["metrics"],
    )
    click.echo(
        f"scored {doc['evaluation']['frames']} frames x {len(methods)} methods -> {opts['out']}/results.md"
    )
    for row in doc["agreement"]:
        verdict = "within" if row["ok"] else "NOT within"
        diff = 100 * row["max_relative_difference"]
        click.echo(
            f"{row['torch']} vs {row['onnxruntime']}: largest metric difference {diff:.3f} % ({verdict} 1 %)"
        )


def sequence_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """--data, --sequences, --max-frames of the downstream commands."""
    func = click.option("--max-frames", type=click.IntRange(min=2), help="First N frames per sequence.")(func)
    func = click.option("--sequences", "sequences_text", help="Sequence numbers, e.g. 0,2 [all].")(func)
    return click.option("--data", required=True, type=PathType, help="Simulated folder (msdnet-data).")(func)


def _downstream(
    task: str, opts: dict[str, Any], place_options: dict[str, Any] | None = None
) -> dict[str, Any]:
    from msdnet.benchmarks.downstream.suite import read_sequences, run_downstream, select_sequences
    from msdnet.runtime.io.datasets import VodDataset

    seqs = select_sequences(
        read_sequences(opts["data"]), int_tuple("--sequences", opts["sequences_text"], 0), opts["max_frames"]
    )
    methods, grid = _methods(opts)
    for m in methods:
        if m.input != "radar":  # a teacher checkpoint: quality scores it on LiDAR, this task cannot
            raise MsdnetError(
                m.source, f"a {m.kind} checkpoint takes LiDAR, not radar: use it with quality only"
            )
    ds = VodDataset(opts["data"])
    evaluation = {"data": str(opts["data"])}
    return run_downstream(task, ds, seqs, methods, grid, opts["out"], evaluation, place_options, opts["seed"])


@click.command("odometry", context_settings={"help_option_names": ["-h", "--help"]})
@sequence_options
@model_options
@one_line_errors
@checks_outputs(out="into")  # before any work
def odometry_command(**opts: Any) -> None:
    """GICP odometry errors of raw radar, the models and LiDAR over simulated sequences."""
    doc = _downstream("odometry", opts)
    for name, r in doc["results"].items():
        o = r["overall"]
        click.echo(f"{name}: t_rel {o['translation_m']:.4f} m/frame, r_rel {o['rotation_deg']:.4f} deg/frame")


@click.command("place", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--ks", "ks_text", default="1,3,5", show_default=True, help="Recall@K values.")
@click.option("--revisit-radius", type=click.FloatRange(min=0, min_open=True), default=5.0, show_default=True)
@click.option("--exclude-recent", type=click.IntRange(min=1), default=50, show_default=True, help="Frames.")
@sequence_options
@model_options
@one_line_errors
@checks_outputs(out="into")  # before any work
def place_command(**opts: Any) -> None:
    """ScanContext Recall@K of raw radar, the models and LiDAR over simulated sequences."""
    ks = int_tuple("--ks", opts["ks_text"], 1)
    place = {"ks": ks, "revisit_radius": opts["revisit_radius"], "exclude_recent": opts["exclude_recent"]}
    doc = _downstream("place", opts, place)
    for name, r in doc["results"].items():
        o = r["overall"]
        recalls = ", ".join(f"R@{k} {100 * v:.1f} %" for k, v in o["recall"].items())
        click.echo(f"{name}: {recalls} ({o['queries']} queries)")
