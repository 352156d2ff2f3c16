"""``msdnet-bench encoders``: the encoder's rulebook and pair forms timed on real Astyx scans."""

from __future__ import annotations

import importlib.util
import re

import pytest
from click.testing import CliRunner

from msdnet.benchmarks.cli import main

pytest.importorskip("torch")
pytest.importorskip("openvino")


def test_tiny_encoder_on_two_frames(astyx_root) -> None:
    args = ["encoders", "--preset", "tiny", "--data", str(astyx_root), "--frames", "2", "--repeats", "1"]
    r = CliRunner().invoke(main, [*args, "--threads", "1"])
    assert r.exit_code == 0, r.output
    head, *rows = r.output.strip().splitlines()
    assert head.startswith("tiny: 2 Astyx frames (median ") and "1 threads" in head
    parity = float(head.rsplit("difference ", 1)[1])
    assert 0 <= parity < 1e-4
    assert len(rows) == 4
    for row, (engine, when) in zip(
        rows, [(e, w) for e in ("onnxruntime", "openvino") for w in ("first", "repeated")], strict=True
    ):
        assert row.startswith(f"  {engine}, {when} call: rulebook "), row
        ms = re.findall(r"(\d+\.\d+) ms", row)
        ratio = float(row.split("pairs / rulebook ")[1].split()[0])
        assert len(ms) == 2 and all(float(v) > 0 for v in ms) and ratio > 0


def test_help_names_the_train_extra_and_no_torch_fails_in_one_line(monkeypatch, tmp_path) -> None:
    help_text = CliRunner().invoke(main, ["encoders", "--help"]).output
    assert "train extra" in help_text and "--preset" in help_text and "--data" in help_text
    bad = CliRunner().invoke(main, ["encoders", "--data", str(tmp_path), "--frames", "0"])
    assert bad.exit_code == 2 and "--frames" in bad.output
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a)
    )
    r = CliRunner().invoke(main, ["encoders", "--data", str(tmp_path)])
    assert r.exit_code == 2 and r.output.strip().count("\n") == 0 and "msdnet[train]" in r.output
