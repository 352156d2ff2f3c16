"""``msdnet-bench params``: parameter counts per module and per model, beside the papers' figures.

The papers compare methods by latency and by size; this is the size half, counted on the torch
models the exported graphs come from (so it needs the ``train`` extra). Models are built on torch's
``meta`` device (shapes only, no memory, no init cost), so the paper preset is instant.

What counts as a model's size: the modules that run at inference. MSDNet's student deploys its
radar encoder, RGFD, noise adapter, light denoiser and the (shared) head; the teacher's LiDAR
encoder and S2D only train it. R2LDM deploys its radar encoder, U-Net and the same head.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from msdnet.benchmarks.args import PRESETS  # training.config.MODEL_PRESETS, named torch-free
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import checks_outputs

if TYPE_CHECKING:
    from torch import nn

    from msdnet.training.config import ModelConfig

PAPER_MILLIONS = {"student": 20.5, "r2ldm": 40.3}  # MSDNet Tab. IV (R2LDM's own paper: 40.1 M)


def _count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def parameter_table(cfg: ModelConfig) -> dict[str, int]:
    """{"<model>.<module>": count, "<model>.total": count} for teacher, student and r2ldm.

    Totals: teacher = encoder + s2d + head (what trains in stage 1); student and r2ldm = their
    inference modules (the head counted once, shared with the teacher).
    """
    import torch

    from msdnet.training.models.assembly import R2LDMModel, StudentModel

    with torch.device("meta"):
        student = StudentModel(cfg)
        r2ldm = R2LDMModel(cfg, student.teacher)
    teacher = student.teacher
    table = {
        "teacher.encoder": _count(teacher.encoder),
        "teacher.s2d": _count(teacher.s2d),
        "teacher.head": _count(teacher.head),
        "student.encoder": _count(student.encoder),
        "student.rgfd": _count(student.rgfd),
        "student.adapter": _count(student.adapter),
        "student.denoiser": _count(student.denoiser),
        "student.head": _count(student.head),
        "r2ldm.encoder": _count(r2ldm.encoder),
        "r2ldm.unet": _count(r2ldm.unet),
        "r2ldm.head": _count(r2ldm.head),
    }
    for model in ("teacher", "student", "r2ldm"):
        table[f"{model}.total"] = sum(v for k, v in table.items() if k.startswith(f"{model}."))
    return table


def format_table(preset: str, table: dict[str, int]) -> str:
    """The table as text, totals beside the paper's figures where it gives one."""
    lines = [f"preset {preset}", f"  {'module':<20}{'parameters':>14}{'paper':>10}"]
    for name, count in table.items():
        paper = PAPER_MILLIONS.get(name.split(".")[0]) if name.endswith(".total") else None
        ref = f"{paper:>9.1f}M" if paper is not None else ""
        lines.append(f"  {name:<20}{count:>14,}{ref:>10}")
    return "\n".join(lines)


def params_markdown(tables: dict[str, dict[str, int]]) -> str:
    """results.md: one row per module, one column per preset, the papers' totals last."""
    presets = list(tables)
    head = "| module | " + " | ".join(presets) + " | paper |"
    lines = ["# Parameters per module and model", "", head, "|---|" + "---:|" * (len(presets) + 1)]
    for name in next(iter(tables.values())):
        paper = PAPER_MILLIONS.get(name.split(".")[0]) if name.endswith(".total") else None
        cells = " | ".join(f"{tables[p][name]:,}" for p in presets)
        lines.append(f"| {name} | {cells} | {f'{paper:.1f} M' if paper is not None else ''} |")
    return "\n".join(lines) + "\n"


@click.command("params", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("presets", nargs=-1, type=click.Choice(PRESETS))
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Folder for results.json and results.md [print only].",
)
@one_line_errors
@checks_outputs(out="into")  # before any work
def params_command(presets: tuple[str, ...], out: Path | None) -> None:
    """Parameter counts of the teacher, the MSDNet student and R2LDM per module, for each PRESET
    (default: all), beside the papers' totals. Needs the train extra (torch):
    pip install 'msdnet[train]'."""
    if importlib.util.find_spec("torch") is None:
        raise MsdnetError("msdnet-bench params", "needs torch: pip install 'msdnet[train]'")
    from msdnet.training.config import MODEL_PRESETS

    tables = {name: parameter_table(MODEL_PRESETS[name]) for name in presets or PRESETS}
    for name, table in tables.items():
        click.echo(format_table(name, table))
    if out is not None:
        from msdnet.benchmarks.quality.report import write_json, write_text

        doc: dict[str, Any] = {"presets": tables, "paper_millions": PAPER_MILLIONS}
        write_json(out / "results.json", doc)
        write_text(out / "results.md", params_markdown(tables))
        click.echo(f"wrote {out / 'results.json'}, {out / 'results.md'}")
