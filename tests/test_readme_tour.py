"""The README's tour runs as written.

The commands are read from the ``bash`` blocks of the README's "A short tour" section and run in
order, in a temporary folder laid out like a checkout (``models/`` and ``../shared`` resolve), with
the installed console scripts. One is not run, by name, with the reason below; its flags are
checked against its ``--help`` instead.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, SHARED_DATA

README = REPO / "README.md"
TOOLS = ("msdnet-infer", "msdnet-node", "msdnet-data", "msdnet-train", "msdnet-export", "msdnet-bench")
NOT_RUN = {
    "msdnet-node": "serves a DDS topic until interrupted; tests/test_live_node.py runs the node on loopback",
}
NEEDS_TORCH = ("msdnet-train", "msdnet-export")


def tour_commands() -> list[str]:
    """Every command of the tour's bash blocks, continuation lines joined, comments dropped."""
    text = README.read_text(encoding="utf-8")
    match = re.search(r"^## A short tour\n(.*?)(?=^## )", text, flags=re.DOTALL | re.MULTILINE)
    assert match, "README has no '## A short tour' section"
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", match.group(1), flags=re.DOTALL):
        block = block.replace("\\\n", " ")
        for line in block.splitlines():
            line = line.split(" # ")[0].strip()
            if line and not line.startswith("#"):
                commands.append(line)
    return commands


def _tool(command: str) -> str:
    return shlex.split(command)[0]


def test_tour_shows_each_command_once_at_least():
    tools = [_tool(c) for c in tour_commands()]
    assert set(tools) == set(TOOLS), tools
    assert all(t in TOOLS for t in tools)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env.setdefault("ORT_DISABLE_TELEMETRY", "1")
    env.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    return env


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    """A folder laid out like the repository: models/ inside, ../shared beside it."""
    work = tmp_path / "msdnet"
    work.mkdir()
    (work / "models").symlink_to(REPO / "models", target_is_directory=True)
    if SHARED_DATA.parent.is_dir():
        (tmp_path / "shared").symlink_to(SHARED_DATA.parent, target_is_directory=True)
    return work


def test_not_run_commands_take_their_flags():
    """The command not run still names only options its --help lists."""
    for command in tour_commands():
        tool = _tool(command)
        if tool not in NOT_RUN:
            continue
        r = subprocess.run([tool, "--help"], capture_output=True, text=True, env=_env(), timeout=120)
        assert r.returncode == 0, r.stderr
        flags = [a.split("=")[0] for a in shlex.split(command)[1:] if a.startswith("--")]
        missing = [f for f in flags if f not in r.stdout]
        assert not missing, f"{tool} --help lacks {missing}"


@pytest.mark.slow
def test_tour_runs_as_written(checkout: Path):
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA}: the tour reads ../shared/data")
    try:
        import torch  # noqa: F401

        has_torch = True
    except ImportError:
        has_torch = False
    ran = []
    for command in tour_commands():
        tool = _tool(command)
        if tool in NOT_RUN or (tool in NEEDS_TORCH and not has_torch):
            continue
        r = subprocess.run(
            command, shell=True, cwd=checkout, capture_output=True, text=True, env=_env(), timeout=600
        )
        assert r.returncode == 0, f"{command}\nexit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
        ran.append(tool)
    tour = checkout / "tour"
    assert any((tour / "dense").glob("*.ply")) and any((tour / "dense").glob("*.png"))
    assert (tour / "frame.png").is_file()
    assert (tour / "quality" / "results.json").is_file()
    if has_torch:
        assert (tour / "my-model" / "manifest.json").is_file()
    assert {"msdnet-infer", "msdnet-data", "msdnet-bench"} <= set(ran)
