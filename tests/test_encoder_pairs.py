"""The encoder's pair form (``encoder_form`` "pairs"): the same weights, only the real neighbour
pairs multiplied; its output equals the rulebook form's within ``GRAPH_REL_TOL`` in torch and in
ONNX (onnxruntime and OpenVINO), on real Astyx frames."""

from __future__ import annotations

import json
import shutil

import numpy as np
import onnxruntime as ort
import pytest
import torch
from export_helpers import one_torch_thread, tiny_config

from msdnet.export.encoder_pairs import pairs_encoder_model, pairs_reference
from msdnet.export.graphs import example_inputs, export_all, export_graph, make_encoder_input, tracing_points
from msdnet.export.manifest import build_manifest, write_manifest
from msdnet.export.verify import E2E_DIFF_TOL, GRAPH_REL_TOL, compare_points
from msdnet.runtime.engine.pairs import CENTRE, DOWN_GROUPS, SUBM_GROUPS, pair_feeds
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.engine.rulebook import KERNEL_TAPS, batch_coords, build_encoder_rulebooks
from msdnet.runtime.engine.voxelize import voxelize
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.datasets import open_dataset
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.model.artifact import load_artifact
from msdnet.training.config import MODEL_PRESETS
from msdnet.training.data.datasets import config_for_dataset
from msdnet.training.models.assembly import build_model
from msdnet.training.nn.encoder import SparseEncoder


@pytest.fixture(scope="module")
def setup(astyx_root, tmp_path_factory):
    """A lite-width radar encoder for Astyx columns (random weights: parity holds for any), its
    rulebook graph, its pair graph, and both forms' inputs of four real Astyx frames."""
    cfg = config_for_dataset(MODEL_PRESETS["lite"], "astyx")
    torch.manual_seed(0)
    enc = SparseEncoder(cfg, "radar").eval()
    folder = tmp_path_factory.mktemp("pairs")
    traced = make_encoder_input([tracing_points(cfg)], cfg.grid, cfg.max_voxels_radar)
    with one_torch_thread():
        inputs = example_inputs(onnx_spec.ENCODER, cfg, traced)
        export_graph(enc, inputs, onnx_spec.ENCODER, folder / "rb.onnx")
    (folder / "pairs.onnx").write_bytes(pairs_encoder_model(enc).SerializeToString())
    ds = open_dataset("astyx", astyx_root, split="val")
    frames = []
    for i in range(4):
        pts = np.ascontiguousarray(ds[i].radar.select(cfg.radar_columns).points, np.float32)
        vox = voxelize(pts, cfg.grid, cfg.max_voxels_radar)
        rb = build_encoder_rulebooks(batch_coords([vox.coords]), cfg.grid.shape_zyx)
        rules = {"voxel_features": vox.features, "subm_rules_0": rb.subm[0]}
        for level in range(1, 4):
            rules |= {f"down_rules_{level}": rb.down[level - 1], f"subm_rules_{level}": rb.subm[level]}
        rules["bev_coords"] = rb.coords[3]
        rules = {k: v.astype(np.float32 if k == "voxel_features" else np.int64) for k, v in rules.items()}
        frames.append((rb, rules, {"voxel_features": vox.features, **pair_feeds(rb, 3)}))
    return enc, folder, frames


def _session(path, threads: int = 2) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.log_severity_level = 3
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


def test_groups_cover_every_tap_once():
    assert sorted(k for g in SUBM_GROUPS for k in g) == sorted(set(range(KERNEL_TAPS)) - {CENTRE})
    assert sorted(k for g in DOWN_GROUPS for k in g) == list(range(KERNEL_TAPS))
    assert (
        len(SUBM_GROUPS) == onnx_spec.PAIR_GROUPS["subm"]
        and len(DOWN_GROUPS) == onnx_spec.PAIR_GROUPS["down"]
    )


def test_pairs_are_the_rulebooks_real_entries(setup):
    """Every real rulebook entry is one pair, nothing else is; padding reads the zero row and
    writes the dropped row; within a tap no output row repeats (so no scatter collides)."""
    _, _, frames = setup
    rb, _, feeds = frames[0]
    assert list(feeds["voxel_counts"]) == [len(c) for c in rb.coords]
    layers = [("subm_0", rb.subm[0], len(rb.coords[0]), SUBM_GROUPS)]
    for level in range(1, 4):
        layers.append((f"down_{level}", rb.down[level - 1], len(rb.coords[level - 1]), DOWN_GROUPS))
        layers.append((f"subm_{level}", rb.subm[level], len(rb.coords[level]), SUBM_GROUPS))
    for layer, rules, n_in, groups in layers:
        for g, taps in enumerate(groups):
            pairs = feeds[f"{layer}_pairs_{g}"]
            assert pairs.dtype == np.int64 and pairs.shape[:2] == (2, len(taps))
            for a, k in enumerate(taps):
                real = pairs[1, a] < len(rules)
                outs = np.nonzero(rules[:, k] < n_in)[0]
                assert np.array_equal(pairs[1, a, real], outs)
                assert np.array_equal(pairs[0, a, real], rules[outs, k])
                assert np.all(pairs[0, a, ~real] == n_in)
    bev = feeds["bev_pairs"]
    d8, h8, w8 = rb.shapes[3]
    assert bev.shape[:2] == (2, d8) and (bev[0] < len(rb.coords[3])).sum() == len(rb.coords[3])
    for z in range(d8):
        cells = bev[1, z][bev[1, z] < h8 * w8]
        assert len(np.unique(cells)) == len(cells)


def test_torch_pair_form_equals_the_encoder(setup):
    enc, _, frames = setup
    with torch.no_grad(), one_torch_thread():
        for _, rules, feeds in frames:
            ref = enc(*(torch.from_numpy(rules[n]) for n in onnx_spec.ENCODER.inputs)).numpy()
            assert _rel(pairs_reference(enc, feeds).numpy(), ref) < GRAPH_REL_TOL


def test_onnx_pair_graph_equals_the_rulebook_graph_at_any_thread_count(setup):
    """onnxruntime: within GRAPH_REL_TOL of the rulebook graph, and the same bytes at 1 and 2
    threads (the cpu provider's promise: each scatter-add's output rows are distinct)."""
    _, folder, frames = setup
    old, new = _session(folder / "rb.onnx"), _session(folder / "pairs.onnx")
    one = _session(folder / "pairs.onnx", 1)
    for _, rules, feeds in frames:
        ref = old.run(None, rules)[0]
        got = new.run(None, feeds)[0]
        assert got.shape == ref.shape and _rel(got, ref) < GRAPH_REL_TOL
        assert got.tobytes() == one.run(None, feeds)[0].tobytes()


def test_openvino_runs_the_pair_graph(setup):
    pytest.importorskip("openvino")
    from msdnet.runtime.providers.openvino_session import OpenVinoSession

    _, folder, frames = setup
    ov = OpenVinoSession((folder / "pairs.onnx").read_bytes(), threads=2)
    old = _session(folder / "rb.onnx")
    for _, rules, feeds in frames[:2]:
        assert _rel(ov.run(None, feeds)[0], old.run(None, rules)[0]) < GRAPH_REL_TOL


def test_a_pair_form_artifact_runs_in_the_pipeline(tmp_path):
    """msdnet-export --encoder-form pairs: the manifest says so, the runtime builds the pairs and
    decodes what the rulebook form decodes; a manifest without the field is the rulebook form."""
    torch.manual_seed(0)
    cfg = tiny_config()
    with one_torch_thread():
        model = build_model("student", cfg).eval()
        folders = {}
        for form in ("rulebook", "pairs"):
            folder = tmp_path / form
            folder.mkdir()
            params, _ = export_all(model, "student", cfg, folder, form)
            write_manifest(folder, build_manifest(folder, "student", cfg, params, "tests", encoder_form=form))
            folders[form] = folder
    manifest = json.loads((folders["pairs"] / "manifest.json").read_text())
    assert manifest["encoder_form"] == "pairs" and "encoder_form" not in json.loads(
        (folders["rulebook"] / "manifest.json").read_text()
    )
    old = Pipeline.from_dir(folders["rulebook"], threads=1)
    new = Pipeline.from_dir(folders["pairs"], threads=1)
    assert "voxel_counts" in new.artifact.specs[0].inputs and "subm_rules_0" in old.artifact.specs[0].inputs
    rng = np.random.default_rng(3)
    grid = cfg.grid
    lo, hi = np.asarray(grid.point_range[:3]), np.asarray(grid.point_range[3:])
    pts = np.zeros((300, len(new.columns)), np.float32)
    pts[:, :3] = lo + (hi - lo) * rng.random((300, 3))
    a, b = old(pts, steps=2), new(pts, steps=2)
    differ, _ = compare_points(a.points, b.points, grid)
    assert len(a.points) > 100 and differ <= E2E_DIFF_TOL * len(a.points)
    bad = tmp_path / "bad"
    shutil.copytree(folders["pairs"], bad)
    write_manifest(bad, {**manifest, "encoder_form": "sideways"})
    with pytest.raises(MsdnetError, match="encoder_form 'sideways' is not one of rulebook, pairs"):
        load_artifact(bad)


def test_export_verifies_the_pair_form_against_torch(tmp_path):
    """``export_model(..., encoder_form="pairs")`` with frames: the encoder graph is checked on its
    own inputs against the torch encoder, and the artifact passes."""
    from msdnet.export.cli import export_model

    torch.manual_seed(0)
    cfg = tiny_config()
    with one_torch_thread():
        model = build_model("student", cfg).eval()
        frames = [tracing_points(cfg, 300, seed) for seed in (1, 2)]
        manifest, report = export_model(
            model, "student", cfg, tmp_path / "m", "tests", frames, "seeded", encoder_form="pairs"
        )
    assert report is not None and report.ok and manifest["encoder_form"] == "pairs"
    assert load_artifact(tmp_path / "m").specs[0].inputs[:2] == ("voxel_features", "voxel_counts")
