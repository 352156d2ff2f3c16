"""Shipped models by name: ``Pipeline.from_dir("astyx-lite")`` and ``msdnet-infer --model
astyx-lite`` find the models inside the package from any working folder; a path still works and
wins over a shipped name; an unknown name is refused in one line that lists the shipped ones."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from msdnet.runtime import Pipeline
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model.artifact import load_artifact
from msdnet.runtime.model.shipped import SHIPPED_DIR, find_model, shipped_name, shipped_names

REPO = Path(__file__).resolve().parents[1]
SHIPPED = ("astyx-lite", "astyx-lite-nodgfd", "astyx-lite-r2ldm", "sim-lite", "sim-lite-r2ldm")


def _astyx_scan(path: Path, rows: int = 300) -> Path:
    """A synthetic radar scan in Astyx's text form (x y z v_r mag), inside astyx-lite's grid."""
    rng = np.random.default_rng(0)
    pts = np.column_stack(
        [rng.uniform(5, 40, rows), rng.uniform(-10, 10, rows), rng.uniform(-1, 2, rows)]
        + [rng.uniform(-5, 5, rows), rng.uniform(30, 60, rows)]
    )
    np.savetxt(path, pts, fmt="%.4f", header="X Y Z V_r Mag", comments="")
    return path


def test_the_shipped_names():
    assert shipped_names() == SHIPPED
    assert shipped_name(SHIPPED_DIR / "astyx-lite") == "astyx-lite"
    assert shipped_name(REPO / "tests") is None


def test_a_name_is_found_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert find_model("astyx-lite") == SHIPPED_DIR / "astyx-lite"
    pipe = Pipeline.from_dir("astyx-lite", threads=1)
    assert pipe.artifact.root == SHIPPED_DIR / "astyx-lite"
    assert pipe.artifact.inputs.columns == ("x", "y", "z", "v_r", "mag")


def test_a_path_still_works_and_wins_over_a_name(tmp_path, monkeypatch):
    assert load_artifact(SHIPPED_DIR / "sim-lite").kind == "student"
    local = tmp_path / "astyx-lite"  # a local folder that shares a shipped model's name
    shutil.copytree(SHIPPED_DIR / "sim-lite-r2ldm", local)
    monkeypatch.chdir(tmp_path)
    assert find_model("astyx-lite") == Path("astyx-lite")
    assert load_artifact("astyx-lite").kind == "r2ldm"


def test_an_unknown_name_lists_the_shipped_ones(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(MsdnetError, match="no shipped model of that name") as err:
        load_artifact("astyx-heavy")
    assert "shipped models: " + ", ".join(SHIPPED) in str(err.value)
    with pytest.raises(MsdnetError, match="model folder not found .shipped models, by name: astyx-lite"):
        load_artifact(tmp_path / "no" / "such")


def _cli(exe: str, *args: object, cwd: Path) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name(exe)
    return subprocess.run(
        [str(script), *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=300
    )


def test_infer_by_name_outside_the_checkout(tmp_path):
    work = tmp_path / "elsewhere"
    work.mkdir()
    scan = _astyx_scan(work / "000001.txt")
    r = _cli(
        "msdnet-infer", scan.name, "--model", "astyx-lite", "--provider", "cpu", "--out", "dense", cwd=work
    )
    assert r.returncode == 0, r.stderr
    out = np.load(work / "dense" / "000001.npy")
    assert out.ndim == 2 and out.shape[0] > 0
    by_path = _cli(
        "msdnet-infer",
        scan,
        "--model",
        SHIPPED_DIR / "astyx-lite",
        "--provider",
        "cpu",
        "--out",
        "p",
        cwd=work,
    )
    assert by_path.returncode == 0, by_path.stderr
    assert (work / "p" / "000001.npy").read_bytes() == (work / "dense" / "000001.npy").read_bytes()


def test_infer_unknown_name_is_one_line(tmp_path):
    scan = _astyx_scan(tmp_path / "000001.txt")
    r = _cli("msdnet-infer", scan, "--model", "astyx-heavy", "--out", tmp_path / "o", cwd=tmp_path)
    assert r.returncode == 2
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith("error: astyx-heavy: ") and ", ".join(SHIPPED) in line
    assert not (tmp_path / "o").exists()


def test_wrong_model_suggests_a_name(tmp_path):
    scan = _astyx_scan(tmp_path / "000001.txt")
    r = _cli("msdnet-infer", scan, "--model", "sim-lite", "--out", tmp_path / "o", cwd=tmp_path)
    assert r.returncode == 2
    (line,) = r.stderr.strip().splitlines()
    assert "the model sim-lite needs" in line and "use --model astyx-lite, which reads" in line


def test_node_unknown_name_is_one_line(tmp_path):
    pytest.importorskip("cyclonedds")
    r = _cli("msdnet-node", "--model", "astyx-heavy", "--topic", "/radar/points", cwd=tmp_path)
    assert r.returncode == 2
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith("error: astyx-heavy: ") and ", ".join(SHIPPED) in line
