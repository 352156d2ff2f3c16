"""The runtime never needs torch: importing any runtime module leaves torch unloaded, and the
Pipeline and msdnet-infer run in a process where ``import torch`` fails."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from export_helpers import make_artifact

from conftest import REPO

BLOCK_TORCH = textwrap.dedent(
    """
    import sys

    class _NoTorch:
        def find_spec(self, name, path=None, target=None):
            if name == "torch" or name.startswith("torch."):
                raise ImportError("torch is blocked in this test")
            return None

    sys.meta_path.insert(0, _NoTorch())
    """
)


def _python(code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=REPO, timeout=120
    )


def test_import_runtime_never_imports_torch():
    code = textwrap.dedent(
        """
        import importlib, pkgutil, sys
        import msdnet.runtime
        assert "torch" not in sys.modules, "import msdnet.runtime loaded torch"
        names = [m.name for m in pkgutil.walk_packages(msdnet.runtime.__path__, "msdnet.runtime.")]
        for name in names:
            importlib.import_module(name)
            assert "torch" not in sys.modules, f"{name} loaded torch"
        from msdnet.runtime import Pipeline, Result, load_artifact  # the public API
        assert "torch" not in sys.modules
        print(len(names))
        """
    )
    r = _python(code)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.strip()) >= 10  # engine.pipeline, model.artifact, io.files, frontends.infer.cli, ...


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return make_artifact(tmp_path_factory.mktemp("art"), "student")


def test_pipeline_and_infer_without_torch(model, vod_root, tmp_path):
    scan = vod_root / "radar" / "training" / "velodyne" / "00549.bin"
    code = BLOCK_TORCH + textwrap.dedent(
        """
        model, scan, out = sys.argv[1:4]
        try:
            import torch  # noqa: F401
            raise SystemExit("torch was importable")
        except ImportError:
            pass
        from msdnet.runtime import Pipeline, read_cloud
        from msdnet.runtime.frontends.infer.cli import main

        res = Pipeline.from_dir(model, threads=1)(read_cloud(scan), steps=2, seed=0)
        print(len(res.points))
        main([scan, "--model", model, "--out", out, "--steps", "2"], standalone_mode=False)
        assert "torch" not in sys.modules
        """
    )
    r = _python(code, str(model), str(scan), str(tmp_path))
    assert r.returncode == 0, r.stderr + r.stdout
    n = int(r.stdout.splitlines()[0])
    assert n > 0 and np.load(tmp_path / "00549.npy").shape == (n, 4)
