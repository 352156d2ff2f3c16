"""Every command's ``--help`` in the user's words: no source paths (``runtime/io/rosbag``), no
design notes outside the repository, no benchmark titled by a paper's table number."""

from __future__ import annotations

import importlib
import re
from collections.abc import Iterator

import click
import pytest

COMMANDS = {
    "msdnet-bench": "msdnet.benchmarks.cli:main",
    "msdnet-data": "msdnet.runtime.frontends.data.cli:main",
    "msdnet-export": "msdnet.export.main:main",
    "msdnet-infer": "msdnet.runtime.frontends.infer.cli:main",
    "msdnet-node": "msdnet.runtime.frontends.live.cli:main",
    "msdnet-train": "msdnet.training.main:main",
}
SOURCE_PATH = re.compile(r"\b(?:runtime|benchmarks|training|export|frontends|tests)/\w|\b\w+\.py\b")
LAB_WORDS = re.compile(r"DESIGN\.md|section \d|Tables? I{1,3}V?\b shape|MSDNet Table", re.IGNORECASE)


def _helps(name: str, cmd: click.Command, parent: click.Context | None = None) -> Iterator[tuple[str, str]]:
    ctx = click.Context(cmd, info_name=name, parent=parent)
    yield ctx.command_path, cmd.get_help(ctx)
    if isinstance(cmd, click.Group):  # a LazyGroup's sub-commands load here
        for sub_name in cmd.list_commands(ctx):
            yield from _helps(sub_name, cmd.get_command(ctx, sub_name), ctx)


@pytest.mark.parametrize("tool", sorted(COMMANDS))
def test_help_texts_name_no_source_paths(tool: str):
    module, attr = COMMANDS[tool].split(":")
    if tool == "msdnet-train":
        pytest.importorskip("torch")
    cmd = getattr(importlib.import_module(module), attr)
    bad = []
    for path, text in _helps(tool, cmd):
        flat = " ".join(text.split())
        bad += [f"{path}: {m.group(0)!r}" for m in SOURCE_PATH.finditer(flat)]
        bad += [f"{path}: {m.group(0)!r}" for m in LAB_WORDS.finditer(flat)]
    assert not bad, "\n".join(bad)


def test_patterns_catch_what_they_should():
    assert SOURCE_PATH.search("a PointCloud2 topic (runtime/io/rosbag)") and SOURCE_PATH.search(
        "see ray_batch.py"
    )
    assert LAB_WORDS.search("statistics (DESIGN.md section 2)") and LAB_WORDS.search("MSDNet Table III: CD")
    assert not SOURCE_PATH.search("ray://HOST:PORT, models/astyx-lite, x/y")
