"""Every ``msdnet-bench`` command checks its arguments and its output before it measures: an output
that is an existing file, an unknown preset, a broken model folder or one of the wrong kind, a model
whose columns the data does not hold: one line, exit 2, nothing measured, no traceback."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from msdnet.benchmarks.cli import main
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL

MODELS = BUNDLED_MODEL.parent


@pytest.fixture(scope="module")
def broken(tmp_path_factory) -> Path:
    """sim-lite with one graph hash changed in its manifest."""
    folder = tmp_path_factory.mktemp("broken") / "model"
    shutil.copytree(BUNDLED_MODEL, folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["graphs"][0]["sha256"] = "0" * 64
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def _refused(args: list[str], says: str, not_done: str = "") -> str:
    r = CliRunner().invoke(main, [str(a) for a in args])
    assert r.exit_code == 2 and says in r.output, r.output
    assert "Traceback" not in r.output and (r.exception is None or isinstance(r.exception, SystemExit))
    if not_done:
        assert not_done not in r.output, r.output  # refused before this work started
    return r.output


def test_outputs_that_are_files_are_refused_before_any_work(tmp_path, astyx_root) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    pytest.importorskip("torch")
    _refused(
        ["params", "tiny", "--out", blocker], f"error: {blocker}: exists and is not a folder", "preset tiny"
    )
    args = ["quality", "--dataset", "astyx", "--data", astyx_root, "--model", MODELS / "astyx-lite"]
    _refused([*args, "--out", tmp_path / "q", "--save", blocker], f"{blocker}: exists and is not a folder")
    assert not (tmp_path / "q").exists()


def test_encoders_checks_preset_model_and_columns_first(tmp_path, broken, astyx_root) -> None:
    pytest.importorskip("torch")
    data = ["--data", astyx_root]
    out = _refused(["encoders", "--preset", "huge", *data], "Invalid value for '--preset'")
    assert "KeyError" not in out
    _refused(
        ["encoders", *data, "--model", broken], f"error: --model: {broken}/encoder.onnx: sha256 mismatch"
    )
    _refused(["encoders", *data, "--model", BUNDLED_MODEL], "--model: ", "Astyx frames (median")
    _refused(["encoders", "--data", tmp_path / "nowhere"], "error: --data: ")


def test_latency_refuses_a_broken_or_r2ldm_before_folder_before_timing(tmp_path, broken) -> None:
    pytest.importorskip("torch")
    base = ["latency", "--quick", "--no-peers", "--out", tmp_path / "lat"]
    _refused([*base, "--before", broken], f"--before: {broken}/encoder.onnx: sha256 mismatch", "measuring")
    r2ldm = MODELS / "astyx-lite-r2ldm"
    _refused([*base, "--before", r2ldm], "--before: ", "measuring")
    _refused([*base, "--before", r2ldm], "holds an R2LDM model, expected an MSDNet (student) model")
    _refused([*base, "--model", MODELS / "astyx-lite", "--r2ldm", MODELS / "astyx-lite"], "--r2ldm: ")
    assert not (tmp_path / "lat" / "results.json").exists()


def test_live_and_node_exit_check_their_model_first(tmp_path, broken, vod_root) -> None:
    pytest.importorskip("cyclonedds")
    live = ["live", "--data", vod_root, "--out", tmp_path / "live"]
    _refused([*live, "--model", broken], "--model: ")
    _refused([*live, "--model", MODELS / "astyx-lite"], "the --data scans have no mag")
    _refused(["node-exit", "--model", broken, "--out", tmp_path / "ne"], "--model: ")
    _refused(["node-exit", "--first-s", "3", "--last-s", "1", "--out", tmp_path / "ne"], "--last-s: ")
