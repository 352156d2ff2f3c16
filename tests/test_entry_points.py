"""One entry per job: every job is a sub-command of its ``msdnet-*`` command, none a ``python -m``
module; ``msdnet-export CHECKPOINT --out DIR`` still runs the export."""

from __future__ import annotations

import re
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from msdnet.export.main import main as export_main
from msdnet.training.main import main as train_main

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", REPO / "CONTRIBUTING.md", *sorted((REPO / "docs").glob("*.md"))]
PAGES += sorted((REPO / "models").glob("*/MODEL.md"))
# modules still run with ``-m``: torchrun starts the trainer so; the tests start the live node and
# its test publisher so, in a fresh interpreter
RUN_AS_MODULE = {"training/cli.py", "runtime/frontends/live/cli.py", "runtime/frontends/live/publish.py"}


def test_no_python_m_in_the_pages():
    hits = [
        f"{page.relative_to(REPO)}:{no}: {line.strip()}"
        for page in PAGES
        for no, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1)
        if "python -m msdnet." in line
    ]
    assert hits == []


def test_no_job_is_a_module_to_run():
    found = {
        str(f.relative_to(REPO))
        for root in ("runtime", "training", "export", "benchmarks")
        for f in (REPO / root).rglob("*.py")
        if re.search(r"^if __name__ == .__main__.:", f.read_text(encoding="utf-8"), re.MULTILINE)
    }
    assert found <= RUN_AS_MODULE, sorted(found - RUN_AS_MODULE)


@pytest.mark.parametrize("group", [train_main, export_main], ids=["msdnet-train", "msdnet-export"])
def test_every_sub_command_loads(group: click.Group):
    pytest.importorskip("torch")
    ctx = click.Context(group, info_name=group.name)
    names = group.list_commands(ctx)
    assert names and all(isinstance(group.get_command(ctx, n), click.Command) for n in names)


def test_group_help_lists_the_jobs_without_loading_them():
    for group, jobs in ((train_main, {"teacher", "student", "r2ldm", "gated-head"}), (export_main, {"gate"})):
        r = CliRunner().invoke(group, ["--help"])
        assert r.exit_code == 0, r.output
        listed = set(re.findall(r"^  ([a-z0-9-]+)  ", r.output, flags=re.MULTILINE))
        assert jobs <= listed, r.output


def test_export_falls_back_to_the_checkpoint_job(tmp_path):
    runner = CliRunner()
    for args in (
        ["nowhere", "--out", str(tmp_path / "m")],
        ["checkpoint", "nowhere", "--out", str(tmp_path / "m")],
    ):
        r = runner.invoke(export_main, args, prog_name="msdnet-export")
        assert r.exit_code == 2, r.output
        assert "nowhere: no such checkpoint" in r.output
    r = runner.invoke(export_main, ["refresh", "--help"], prog_name="msdnet-export")
    assert r.exit_code == 0 and r.output.startswith("Usage: msdnet-export refresh [OPTIONS] MODEL")


def test_train_kinds_take_the_training_options():
    pytest.importorskip("torch")
    ctx = click.Context(train_main, info_name="msdnet-train")
    teacher = train_main.get_command(ctx, "teacher")
    names = {p.name for p in teacher.params}
    assert "kind" not in names and {"dataset", "data", "out", "preset"} <= names
