"""``msdnet-export refresh``: a model exported before the head's up-sampling became one
``ConvTranspose`` is re-exported with the same weights and calibration, and runs the same."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from click.testing import CliRunner
from export_helpers import make_checkpoint, one_torch_thread

from msdnet.export.refresh import main as refresh_main
from msdnet.export.refresh import refresh_model
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.errors import MsdnetError
from msdnet.training.nn.head import up_export_style


def _ops(path: Path) -> set[str]:
    return {n.op_type for n in onnx.load(str(path)).graph.node}


@pytest.fixture(scope="module")
def legacy(tmp_path_factory) -> Path:
    """A tiny student exported the old way (1x1x1 conv + 8-D Transpose), with a gate, a threshold,
    a calibration record and a MODEL.md as a shipped folder has them."""
    from msdnet.export.cli import export_model
    from msdnet.training.recipe.checkpoint import load_checkpoint

    root = tmp_path_factory.mktemp("legacy")
    model, cfg, _ = load_checkpoint(make_checkpoint(root / "ckpt", "student"))
    with one_torch_thread(), up_export_style("depth_to_space"):
        export_model(model, "student", cfg, root / "onnx", "runs/x/best")
    manifest = json.loads((root / "onnx" / "manifest.json").read_text())
    manifest |= {"threshold": 0.3, "gate": 0.2, "gate_calibration": {"gate": 0.2, "frames": 7}}
    (root / "onnx" / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    (root / "onnx" / "MODEL.md").write_text("# a model card\n")
    return root / "onnx"


def test_refresh_rewrites_the_heads_and_keeps_everything_else(legacy, tmp_path):
    assert "ConvTranspose" not in _ops(legacy / "recon_head.onnx")
    with one_torch_thread():
        r = refresh_model(legacy, tmp_path / "new")
    new = tmp_path / "new"
    for head in ("recon_head.onnx", "recon_head_sparse.onnx"):
        assert "ConvTranspose" in _ops(new / head)
    assert set(r.changed) == {"recon_head.onnx", "recon_head_sparse.onnx"}  # the rest: same bytes
    for f in ("encoder.onnx", "rgfd_adapter.onnx", "denoiser_step.onnx"):
        assert (new / f).read_bytes() == (legacy / f).read_bytes()
    old_m, new_m = (json.loads((d / "manifest.json").read_text()) for d in (legacy, new))
    for key in ("threshold", "gate", "gate_calibration", "source", "config", "diffusion"):
        assert new_m[key] == old_m[key]
    assert (new / "MODEL.md").read_text() == "# a model card\n"
    assert new_m["refreshed"]["changed"] == list(r.changed) and r.max_rel < 1e-4
    # same points from a few scans, with the manifest's threshold and gate
    a, b = Pipeline.from_dir(legacy, threads=1), Pipeline.from_dir(new, threads=1)
    rng = np.random.default_rng(3)
    for _ in range(3):
        pts = np.zeros((200, len(a.columns)), np.float32)
        pts[:, :3] = rng.uniform([0, -10, -1], [40, 10, 2], (200, 3))
        pa, pb = a(pts, seed=1).points, b(pts, seed=1).points
        assert pa.shape == pb.shape and np.allclose(pa, pb, atol=1e-4)


def test_refresh_in_place_and_a_refreshed_folder_refreshes_to_the_same_bytes(legacy, tmp_path):
    import shutil

    folder = tmp_path / "model"
    shutil.copytree(legacy, folder)
    with one_torch_thread():
        refresh_model(folder)  # in place
        first = {f.name: f.read_bytes() for f in folder.glob("*.onnx")}
        again = refresh_model(folder, tmp_path / "again")
    assert again.changed == ()
    assert {f.name: f.read_bytes() for f in (tmp_path / "again").glob("*.onnx")} == first
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp left


def test_refresh_refuses_in_one_line(legacy, tmp_path):
    import shutil

    signed = tmp_path / "signed"
    shutil.copytree(legacy, signed)
    (signed / "manifest.sig").write_bytes(b"x")
    with pytest.raises(MsdnetError, match="signed"):
        refresh_model(signed, tmp_path / "out")
    (tmp_path / "file").write_text("x")
    res = CliRunner().invoke(refresh_main, [str(legacy), "--out", str(tmp_path / "file")])
    assert res.exit_code != 0 and "not a folder" in res.output and "Traceback" not in res.output


@pytest.mark.parametrize("up", ["conv_transpose", "depth_to_space"])
def test_latency_random_models_export_the_asked_up_sampling(up, tmp_path):
    """``msdnet-bench latency --up-sampling``: old and new head graphs, timed side by side."""
    from msdnet.benchmarks.latency.models import preset_config, random_pair

    with one_torch_thread():
        pair = random_pair(preset_config("tiny"), tmp_path, up=up)
    for m in (pair.msdnet, pair.r2ldm):
        assert ("ConvTranspose" in _ops(m.folder / "recon_head.onnx")) == (up == "conv_transpose")
