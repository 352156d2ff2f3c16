"""``msdnet-export``: graphs + manifest, ``--verify`` (torch vs onnxruntime), atomic publishing,
and the external-data check of runtime/model/onnx_check.py against the real ``onnx`` schema."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from click.testing import CliRunner
from export_helpers import make_checkpoint, tiny_config
from onnx import TensorProto, helper, numpy_helper

from msdnet.export import verify
from msdnet.export.cli import main
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import file_digest, load_artifact
from msdnet.runtime.model.onnx_check import SUBSET, external_tensors
from msdnet.runtime.spec.ddim import alphas_cumprod
from msdnet.training.models.assembly import build_model


@pytest.fixture(autouse=True)
def one_torch_thread():
    """torch's OpenMP pool on a shared 2-core machine costs ~1000x on tiny ops; --threads 1 too."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def student_ckpt(tmp_path_factory) -> Path:
    return make_checkpoint(tmp_path_factory.mktemp("ckpt") / "student", "student")


def _export(args: list[str]):
    return CliRunner().invoke(main, [*(str(a) for a in args), "--threads", "1"])


def test_export_student_verify_on_vod(student_ckpt, vod_root, tmp_path):
    out = tmp_path / "model"
    r = _export([student_ckpt, "--out", out, "--verify", "--data", vod_root, "--dataset", "vod"])
    assert r.exit_code == 0, r.output
    for spec in (*onnx_spec.MSDNET_GRAPHS, *onnx_spec.OPTIONAL_GRAPHS):
        line = next(ln for ln in r.output.splitlines() if ln.strip().startswith(spec.file))
        assert line.rstrip().endswith("ok"), line
    assert "end to end: 3 frames x 50 steps" in r.output
    m = json.loads((out / "manifest.json").read_text())
    cfg = tiny_config("vod")
    assert m["format_version"] == onnx_spec.FORMAT_VERSION and m["model_kind"] == "student"
    assert m["opset"] == onnx_spec.OPSET and m["versions"]["torch"] == torch.__version__
    assert m["versions"]["onnx"] == onnx.__version__
    assert m["config"]["bev_channels"] == cfg.bev_channels
    d = m["diffusion"]
    assert (d["start_step"], d["sample_steps"], d["interval"]) == (100, 50, 2.0)  # m = 100, config.py
    np.testing.assert_allclose(d["alphas_cumprod"], alphas_cumprod(cfg.diffusion))
    assert m["threshold"] == cfg.threshold
    assert m["input"]["columns"] == list(cfg.radar_columns)
    assert len(m["input"]["normalisation"]["scale"]) == len(cfg.radar_columns)
    assert m["parameters"]["total"] == sum(v for k, v in m["parameters"].items() if k != "total")
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["manifest.json", *(s.file for s in (*onnx_spec.MSDNET_GRAPHS, *onnx_spec.OPTIONAL_GRAPHS))]
    )
    for g in m["graphs"]:
        assert (g["bytes"], g["sha256"]) == file_digest(out / g["file"])
    ver = m["verification"]
    assert ver["ok"] and all(g["max_rel"] <= 1e-4 and g["cosine"] > 0.999999 for g in ver["graphs"])
    e2e = ver["end_to_end"]
    assert e2e["points_torch"] > 1000 and e2e["differ"] == 0
    assert not list(tmp_path.glob(".*tmp")), "temporary folder left behind"


def test_export_r2ldm_verify_random_frames(tmp_path):
    ckpt = make_checkpoint(tmp_path / "r2ldm", "r2ldm")
    out = tmp_path / "model"
    r = _export([ckpt, "--out", out, "--verify", "--frames", "2"])
    assert r.exit_code == 0, r.output
    assert "2 random frames" in r.output
    art = load_artifact(out)
    assert art.kind == "r2ldm" and [s.file for s in art.specs] == [
        s.file for s in (*onnx_spec.R2LDM_GRAPHS, *onnx_spec.OPTIONAL_GRAPHS)
    ]
    cfg = tiny_config()
    assert art.diffusion.start_step == cfg.diffusion.num_train_steps  # pure noise start
    assert art.diffusion.sample_steps == cfg.r2ldm_sample_steps


def test_verify_fails_beyond_tolerance(student_ckpt, tmp_path, monkeypatch):
    """A tolerance nothing can meet: exit 1, FAIL printed, --out neither created nor replaced."""
    out = tmp_path / "model"
    monkeypatch.setattr(verify, "GRAPH_REL_TOL", 0.0)
    r = _export([student_ckpt, "--out", out, "--verify", "--frames", "1"])
    assert r.exit_code == 1, r.output
    assert "FAIL" in r.output and not out.exists()
    assert not list(tmp_path.glob(".*tmp"))


def test_verify_catches_a_wrong_graph(tmp_path):
    """Graphs of one model verified against a model with other weights: every graph fails."""
    torch.manual_seed(0)
    cfg = tiny_config()
    exported, other = build_model("student", cfg).eval(), build_model("student", cfg).eval()
    with torch.no_grad():  # the denoiser's head starts at zero in both: give them different weights
        for m in (exported, other):
            torch.nn.init.normal_(m.denoiser.head[2].weight, std=0.1)
    from msdnet.export.graphs import export_all, tracing_points
    from msdnet.export.manifest import build_manifest, write_manifest

    params, _ = export_all(exported, "student", cfg, tmp_path)
    write_manifest(tmp_path, build_manifest(tmp_path, "student", cfg, params, "test"))
    frames = [tracing_points(cfg, 300, seed=5)]
    good = verify.verify_artifact(exported, "student", cfg, tmp_path, frames, "random")
    bad = verify.verify_artifact(other, "student", cfg, tmp_path, frames, "random")
    assert good.ok and not bad.ok
    assert all(not g.ok for g in bad.graphs) and bad.e2e.differ > 0


def test_export_replaces_an_artifact_but_not_other_folders(student_ckpt, tmp_path):
    out = tmp_path / "model"
    assert _export([student_ckpt, "--out", out]).exit_code == 0
    first = (out / "manifest.json").read_text()
    r = _export([student_ckpt, "--out", out])
    assert r.exit_code == 0, r.output and (out / "manifest.json").read_text() == first
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    r = _export([student_ckpt, "--out", other])
    assert r.exit_code == 2 and "refusing to replace it" in r.output
    assert (other / "keep.txt").read_text() == "mine"


def test_threshold_option_goes_into_the_manifest(student_ckpt, tmp_path):
    r = _export([student_ckpt, "--out", tmp_path / "m", "--threshold", "0.3"])
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert m["threshold"] == 0.3 and m["config"]["threshold"] == 0.3
    assert _export([student_ckpt, "--out", tmp_path / "n", "--threshold", "1.5"]).exit_code == 2


def test_steps_option_sets_the_manifest_default(student_ckpt, tmp_path):
    m0 = load_artifact(_exported(student_ckpt, tmp_path / "a"))
    r = _export([student_ckpt, "--out", tmp_path / "m", "--steps", "2"])
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert m["diffusion"]["sample_steps"] == 2 != m0.diffusion.sample_steps
    assert m["diffusion"]["interval"] == m["diffusion"]["start_step"] / 2
    assert m["config"]["diffusion"]["sample_steps"] == 2
    assert load_artifact(tmp_path / "m").diffusion.sample_steps == 2
    too_many = _export([student_ckpt, "--out", tmp_path / "n", "--steps", "100000"])
    assert too_many.exit_code == 2 and "exceeds the start step" in too_many.output


def _exported(ckpt: Path, out: Path) -> Path:
    r = _export([ckpt, "--out", out])
    assert r.exit_code == 0, r.output
    return out


def test_export_refuses_a_teacher(tmp_path):
    ckpt = make_checkpoint(tmp_path / "teacher", "teacher")
    r = _export([ckpt, "--out", tmp_path / "m"])
    assert r.exit_code == 2
    assert r.output.startswith("error: ") and "teacher checkpoint cannot be exported" in r.output


def test_subset_schema_matches_onnx():
    """The field numbers runtime/model/onnx_check.py declares are those of the real onnx.proto."""
    for msg, fields in SUBSET.items():
        desc = getattr(onnx, msg).DESCRIPTOR
        for name, number, kind, repeated in fields:
            f = desc.fields_by_name[name]
            assert f.number == number, (msg, name)
            assert f.is_repeated == repeated, (msg, name)
            if f.message_type is not None:
                assert f.message_type.name == kind, (msg, name)


def _matmul_model() -> onnx.ModelProto:
    w = numpy_helper.from_array(np.ones((64, 64), np.float32), "weight")
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 64])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 64])
    g = helper.make_graph([helper.make_node("MatMul", ["x", "weight"], ["y"])], "g", [x], [y], [w])
    return helper.make_model(g)


def test_external_tensors_found(tmp_path):
    model = _matmul_model()
    assert external_tensors(model.SerializeToString()) == []
    path = tmp_path / "m.onnx"
    onnx.save_model(model, path, save_as_external_data=True, location="w.bin", size_threshold=0)
    assert external_tensors(path.read_bytes()) == ["weight"]
    with pytest.raises(ValueError, match="not an ONNX model"):
        external_tensors(b"\xff\xff\xff\xff not protobuf")
