"""Parameter counts per module and per model, beside the papers' figures.

``python -m msdnet.training.params [tiny|lite|paper ...]`` prints the table. Models are built on
torch's ``meta`` device (shapes only, no memory, no init cost), so the paper preset is instant.

What counts as a model's size: the modules that run at inference. MSDNet's student deploys its
radar encoder, RGFD, noise adapter, light denoiser and the (shared) head — the teacher's LiDAR
encoder and S2D only train it. R2LDM deploys its radar encoder, U-Net and the same head.
"""

from __future__ import annotations

import sys

import torch
from torch import nn

from msdnet.training.config import MODEL_PRESETS, ModelConfig
from msdnet.training.models import R2LDMModel, StudentModel

PAPER_MILLIONS = {"student": 20.5, "r2ldm": 40.3}  # MSDNet Tab. IV (R2LDM's own paper: 40.1 M)


def _count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def parameter_table(cfg: ModelConfig) -> dict[str, int]:
    """{"<model>.<module>": count, "<model>.total": count} for teacher, student and r2ldm.

    Totals: teacher = encoder + s2d + head (what trains in stage 1); student and r2ldm = their
    inference modules (the head counted once, shared with the teacher).
    """
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


def main(argv: list[str] | None = None) -> int:
    """Print the parameter table of each named preset (default: all)."""
    names = (argv if argv is not None else sys.argv[1:]) or list(MODEL_PRESETS)
    for name in names:
        if name not in MODEL_PRESETS:
            print(f"error: unknown preset {name!r} (one of {', '.join(MODEL_PRESETS)})")
            return 2
        print(format_table(name, parameter_table(MODEL_PRESETS[name])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
