"""Options of ``msdnet-infer`` that do not apply to the given inputs: refused, or noted in one line.

An option the chosen mode never reads is refused (exit 2, one line naming it), so nothing the
user asked for is silently ignored:

- ``--layout`` / ``--columns`` name the columns of headerless ``.bin`` inputs; with no ``.bin``
  among the inputs (``.pcd``, ``.ply``, ``.npy``, ``.txt`` name their columns or take them from
  their shape), with ``--dataset`` or with ``--topic`` they are refused; with some ``.bin``
  inputs among others a note says which inputs they apply to.
- ``--split`` / ``--frames`` only with ``--dataset``; ``--field`` / ``--bag-storage`` only with
  ``--topic`` (``cli.main`` refuses those in file mode); ``--workers`` above 1 not with
  ``--dataset`` (one process) or ``--topic``; ``--ray-timeout`` only with ``--ray``;
  ``--format`` not with ``--topic`` (the output is a bag).
- ``-v`` prints only with ``--provider auto[-bf16]``: noted otherwise.

Only options given on the command line count (``click``'s parameter source), so defaults never
trip a check.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import click
from click.core import ParameterSource

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.files import READ_FORMATS

BIN = ".bin"


def given(ctx: click.Context, name: str) -> bool:
    """Whether option ``name`` (the parameter's Python name) was given on the command line."""
    return ctx.get_parameter_source(name) in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT)


def _flag(ctx: click.Context, *names: str) -> str:
    """The command-line spelling of the first given parameter of ``names``: ``--layout``."""
    for name in names:
        if given(ctx, name):
            param = next(p for p in ctx.command.params if p.name == name)
            return max(param.opts, key=len)
    return names[0]


def bin_inputs(inputs: Sequence[Path]) -> tuple[int, int]:
    """(``.bin`` inputs, other readable inputs) among files and the files directly in folders."""
    bins = others = 0
    for item in inputs:
        try:
            files = sorted(item.iterdir()) if item.is_dir() else [item]
        except OSError:  # an unreadable folder is refused later, naming it
            continue
        for f in files:
            suffix = f.suffix.lower()
            if suffix == BIN:
                bins += 1
            elif suffix in READ_FORMATS:
                others += 1
    return bins, others


def check_option_use(
    ctx: click.Context,
    inputs: Sequence[Path],
    mode: str,
    provider: str,
    note: Callable[[str], None],
) -> None:
    """Refuse (MsdnetError) an option given on the command line that ``mode`` (``"files"``,
    ``"dataset"`` or ``"topic"``) does not read; ``note`` one line for one that applies to some
    inputs only, or does nothing here."""
    layout_given = given(ctx, "layout") or given(ctx, "bin_columns")
    flag = _flag(ctx, "layout", "bin_columns")
    if layout_given and mode != "files":
        raise MsdnetError(flag, f"names the columns of .bin files; it does not apply with --{mode}")
    if layout_given:
        bins, others = bin_inputs(inputs)
        if not bins:
            raise MsdnetError(
                flag,
                "names the columns of .bin files, and no input is a .bin (.pcd, .ply, .npy and .txt "
                "name their columns or take them from their shape)",
            )
        if others:
            note(f"note: {flag} applies to the {bins} .bin inputs only, not to the {others} others")
    if mode != "dataset" and (given(ctx, "split") or given(ctx, "max_frames")):
        raise MsdnetError("--split/--frames", "only apply with --dataset")
    if mode != "files" and given(ctx, "workers") and ctx.params.get("workers", 1) > 1:
        raise MsdnetError("--workers", f"--{mode} runs in one process")
    if given(ctx, "ray_timeout") and ctx.params.get("ray_address") is None:
        raise MsdnetError("--ray-timeout", "only applies with --ray ADDRESS")
    if mode == "topic" and given(ctx, "fmt"):
        raise MsdnetError("--format", "--topic writes a ROS 2 bag; --format is for file outputs")
    if given(ctx, "verbose") and provider.strip().lower() not in ("auto", "auto-bf16"):
        note(f"note: -v prints the engine picks of --provider auto only; --provider {provider} has none")
