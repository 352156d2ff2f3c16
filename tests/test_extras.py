"""A runtime-only install: the engine runs with no extra, every command's ``--help`` works, and a
command that needs a missing extra ends in one line naming the ``pip install`` (exit 2).

The checks run in subprocesses that hide every extra's packages from the import system (as if
``pip install msdnet`` had installed the base dependencies alone): ``importlib.util.find_spec``
finds none of them and ``import`` raises ``ModuleNotFoundError``, as in such an install.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from msdnet.runtime.errors import BUNDLES, EXTRA_OF

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
SCRIPTS = PYPROJECT["scripts"]
EXTRAS = PYPROJECT["optional-dependencies"]
HIDDEN = sorted(EXTRA_OF)  # every package an extra brings, by its import name
# import name -> distribution name, where they differ
DISTRIBUTION = {
    "yaml": "pyyaml",
    "rerun": "rerun-sdk",
    "foxglove": "foxglove-sdk",
    "small_gicp": "small_gicp",
}

HIDE = f"""
import sys
HIDDEN = {set(HIDDEN)!r}
assert not HIDDEN & {{m.partition(".")[0] for m in sys.modules}}, "imported before the test hid it"

class _Hide:
    def __init__(self, finder):
        self.finder = finder

    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in HIDDEN:
            return None
        find = getattr(self.finder, "find_spec", None)
        return None if find is None else find(name, path, target)

    def __getattr__(self, attr):
        return getattr(self.finder, attr)

sys.meta_path[:] = [_Hide(f) for f in sys.meta_path]
"""


def _python(code: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", HIDE + code], cwd=cwd, capture_output=True, text=True, timeout=timeout
    )


def _command(script: str, *args: object, cwd: Path) -> subprocess.CompletedProcess:
    module, attr = SCRIPTS[script].split(":")
    argv = [script, *map(str, args)]
    return _python(f"sys.argv = {argv!r}\nfrom {module} import {attr}\n{attr}()", cwd)


def test_the_engine_runs_without_any_extra(tmp_path):
    scan = tmp_path / "scan.npy"
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(5, 40, 300), rng.uniform(-10, 10, 300), rng.uniform(-1, 2, 300)])
    np.save(scan, np.column_stack([pts, rng.uniform(-5, 5, (300, 2))]).astype(np.float32))
    code = f"""
from msdnet.runtime import Pipeline
from msdnet.runtime.io.files import read_cloud
pipe = Pipeline.from_dir("astyx-lite", threads=1)
cloud = read_cloud({str(scan)!r}, columns=pipe.artifact.inputs.columns)
out = pipe(cloud, seed=0)
loaded = sorted(m for m in sys.modules if m.partition(".")[0] in HIDDEN | {{"scipy", "matplotlib"}})
print(len(out.points), loaded)
"""
    r = _python(code, tmp_path)
    assert r.returncode == 0, r.stderr
    count, loaded = r.stdout.split(" ", 1)
    assert int(count) > 0 and loaded.strip() == "[]"


def test_importing_the_pipeline_loads_no_tool():
    """Where the tools are installed: the Pipeline loads no matplotlib and no part of scipy
    (numba's own version check imports the bare ``scipy`` package when it is there)."""
    tools = ("matplotlib", "scipy.spatial", "scipy.sparse", "scipy.linalg", "scipy.stats", "pypatchworkpp")
    code = (
        "import sys\nfrom msdnet.runtime.engine.pipeline import Pipeline\n"
        "from msdnet.runtime import Pipeline as P\n"
        f"print(sorted(m for m in sys.modules if m.startswith({(*tools, 'torch')!r})))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_every_help_works_without_extras(script, tmp_path):
    r = _command(script, "--help", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"Usage: {script}")


MISSING = [
    ("msdnet-infer", ["scan.npy", "--out", "o", "--png"], "--png", "pictures"),
    ("msdnet-infer", ["scan.npy", "--out", "o", "--format", "ply"], "--format ply", "formats"),
    ("msdnet-infer", ["scan.pcd", "--out", "o"], ".pcd inputs", "formats"),
    ("msdnet-node", ["--topic", "/radar/points"], "", "live"),
    (
        "msdnet-data",
        ["show", "--dataset", "sim", "--data", "d", "--frame", "0", "--out", "f.png"],
        "",
        "pictures",
    ),
    ("msdnet-data", ["pair", "x.bag", "--radar-topic", "/a", "--lidar-topic", "/b", "--out", "p"], "", "ros"),
    ("msdnet-train", ["teacher", "--dataset", "astyx", "--data", "d", "--out", "t"], "", "train"),
    ("msdnet-train", ["gated-head", "--help"], "", "train"),
    ("msdnet-export", ["ckpt", "--out", "m"], "", "train"),
    (
        "msdnet-bench",
        ["quality", "--dataset", "sim", "--data", "d", "--model", "sim-lite", "--out", "q"],
        "",
        "bench",
    ),
]


@pytest.mark.parametrize(("script", "args", "what", "extra"), MISSING, ids=lambda v: str(v)[:20])
def test_a_missing_extra_is_one_line(script, args, what, extra, tmp_path):
    np.save(tmp_path / "scan.npy", np.zeros((4, 5), np.float32))
    (tmp_path / "scan.pcd").write_text("VERSION .7\nDATA ascii\n")
    r = _command(script, *args, cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith(f"error: {script}" if not what else f"error: {what}: "), line
    assert f"pip install 'msdnet[{extra}]'" in line and "Traceback" not in line


def _requirement_names(extra: str) -> set[str]:
    return {re.split(r"[<>=\[ ;]", req, maxsplit=1)[0].lower() for req in EXTRAS[extra]}


def test_each_extra_named_brings_its_packages():
    for package, extra in EXTRA_OF.items():
        assert DISTRIBUTION.get(package, package).lower() in _requirement_names(extra), (package, extra)
    for extra, packages in BUNDLES.items():
        for package in packages:
            assert DISTRIBUTION.get(package, package).lower() in _requirement_names(extra), (package, extra)


def test_the_base_is_the_engine():
    names = {re.split(r"[<>=\[ ;]", req, maxsplit=1)[0].lower() for req in PYPROJECT["dependencies"]}
    assert names == {"numpy", "numba", "onnxruntime", "click", "tqdm"}
