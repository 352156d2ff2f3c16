"""The tree stays clean under ruff check and ruff format."""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import pytest

from conftest import REPO


def _ruff() -> list[str]:
    if importlib.util.find_spec("ruff") is None:
        pytest.skip("ruff is not installed (pip install -e '.[dev]')")
    return [sys.executable, "-m", "ruff"]


def test_ruff_check():
    r = subprocess.run([*_ruff(), "check", "."], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_ruff_format():
    r = subprocess.run([*_ruff(), "format", "--check", "."], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_no_file_names_a_folder_of_the_machine():
    """Committed text (code, docs, results) names paths relative to the repository, never the
    folders of the machine it was written on."""
    import re

    files = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True)
    pattern = re.compile(r"(?<![\w.$~])/(?:tmp|work|root|home|Users)/[\w.-]")
    hits = []
    for name in files.stdout.splitlines():
        if not name.endswith((".py", ".md", ".json", ".txt", ".toml", ".sh", ".yaml", ".yml", ".cfg")):
            continue
        if name.startswith("tests/"):  # tests build such paths on purpose (tmp_path)
            continue
        path = REPO / name
        if not path.is_file():
            continue
        for no, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if pattern.search(line):
                hits.append(f"{name}:{no}: {line.strip()[:120]}")
    assert not hits, "\n".join(hits)


def test_shown_path_is_relative():
    from msdnet.benchmarks.machine import shown_path

    assert shown_path(REPO / "models" / "sim-lite") == "models/sim-lite"
    assert shown_path("/nowhere/deep/a/b") == "a/b"


def test_python_version_supported():
    assert sys.version_info >= (3, 10)
