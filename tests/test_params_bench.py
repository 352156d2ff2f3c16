"""``msdnet-bench params``: the parameter table against the papers' totals, from the command."""

from __future__ import annotations

import importlib.util
import json

from click.testing import CliRunner

from msdnet.benchmarks.cli import main
from msdnet.benchmarks.params import PAPER_MILLIONS, PRESETS, parameter_table
from msdnet.training.config import MODEL_PRESETS


def test_presets_are_the_training_presets() -> None:
    assert PRESETS == tuple(MODEL_PRESETS)


def test_command_prints_and_writes_the_table(tmp_path) -> None:
    r = CliRunner().invoke(main, ["params", "tiny", "paper", "--out", str(tmp_path / "p")])
    assert r.exit_code == 0, r.output
    assert "preset tiny" in r.output and "preset paper" in r.output and "preset lite" not in r.output
    assert f"{PAPER_MILLIONS['student']:.1f}M" in r.output
    doc = json.loads((tmp_path / "p" / "results.json").read_text())
    assert doc["presets"]["paper"] == parameter_table(MODEL_PRESETS["paper"])
    md = (tmp_path / "p" / "results.md").read_text()
    assert "| student.total |" in md and "20.5 M" in md


def test_help_names_the_train_extra_and_no_torch_fails_in_one_line(monkeypatch) -> None:
    assert "train extra" in CliRunner().invoke(main, ["params", "--help"]).output
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a)
    )
    r = CliRunner().invoke(main, ["params", "tiny"])
    assert r.exit_code == 2 and r.output.strip().count("\n") == 0 and "msdnet[train]" in r.output
