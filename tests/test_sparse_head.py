"""Coarse-to-fine head: torch sparse path, sparse decoder, exported graph in the Pipeline, gate."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch
from export_helpers import make_artifact, one_torch_thread, tiny_config

from msdnet.export.gate import calibrate_gate, keep_all_gate
from msdnet.export.manifest import write_manifest
from msdnet.runtime.engine.decode import decode_packed, decode_sparse, packed_shape
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model.artifact import load_artifact
from msdnet.runtime.spec.grid import GRID_PRESETS, GridConfig
from msdnet.training.models.assembly import bev_shape
from msdnet.training.nn.head import ReconHead
from msdnet.training.nn.head_gated import FixedGroupNorm, GatedReconHead
from msdnet.training.nn.heads import build_head

ODD = GridConfig((0.0, 0.0, 0.0, 2.2, 1.8, 1.5), (0.2, 0.2, 0.3))  # 11 x 9 x 5: odd on every axis


def _gate_occupancy(head: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """Every half-scale voxel's gate occupancy, from the dense multi-scale outputs: its own
    occupancy (ReconHead), or the smaller of its own and its 1/4 parent's (SparseReconHead,
    GatedReconHead)."""
    (l4, _), (l2, _), _ = head.multi_scale(x)
    own = torch.sigmoid(l2)[0, 0]  # (D2, H2, W2)
    if type(head) is ReconHead:
        return own.reshape(-1)
    d2, h2, w2 = own.shape
    up = _up(torch.sigmoid(l4)[0, 0], 2)
    return torch.minimum(own, up[:d2, :h2, :w2]).reshape(-1)


def _up(v: torch.Tensor, k: int) -> torch.Tensor:
    """(D, H, W) -> (k D, k H, k W), each voxel repeated."""
    return v.repeat_interleave(k, 0).repeat_interleave(k, 1).repeat_interleave(k, 2)


def _fold_random(head: torch.nn.Module) -> None:
    """Statistics in the fixed norm as calibration would set them, not 0 / 1."""
    norm = head.fixed_norm()
    norm.fold(torch.rand(norm.num_groups) - 0.5, torch.rand(norm.num_groups) * 2 + 0.2)


@pytest.mark.parametrize("kind", ["dense", "sparse", "gated"])
def test_sparse_children_equal_packed(kind: str) -> None:
    torch.manual_seed(0)
    cfg = dataclasses.replace(tiny_config(), head_kind=kind)
    head = build_head(cfg).eval()
    if isinstance(head, GatedReconHead):
        _fold_random(head)
    x = torch.randn(1, *bev_shape(cfg))
    with one_torch_thread(), torch.no_grad():
        occ, off = head.packed(x)  # (1, 8, D2, H2, W2), (1, 8, 3, D2, H2, W2)
        s_occ, s_off, vox, g_occ = head.sparse(x, torch.zeros(1))
        half = _gate_occupancy(head, x)
        gate = torch.quantile(half, 0.6).reshape(1)
        k_occ, _, k_vox, k_g = head.sparse(x, gate)
    assert vox.tolist() == list(range(occ[0, 0].numel()))  # gate 0 keeps every voxel, in order
    torch.testing.assert_close(s_occ, occ.reshape(8, -1).t(), rtol=0, atol=1e-6)
    torch.testing.assert_close(s_off, off.reshape(8, 3, -1).permute(2, 0, 1), rtol=0, atol=1e-6)
    torch.testing.assert_close(g_occ, half, rtol=0, atol=1e-6)
    assert torch.equal(k_vox, torch.nonzero(half > gate).reshape(-1)) and 0 < len(k_vox) < len(vox)
    assert torch.all(k_g > gate) and torch.equal(k_occ, s_occ[k_vox])


def test_sparse_head_is_per_voxel_below_the_coarsest_level() -> None:
    """Only the 1/8 and 1/4 levels have 3x3x3 kernels and volume norms; every layer below works
    per voxel (which is what lets ``sparse`` compute any subset of voxels exactly)."""
    head = build_head(dataclasses.replace(tiny_config(), head_kind="sparse"))
    spatial = {
        n for n, m in head.named_modules() if isinstance(m, torch.nn.Conv3d) and m.kernel_size != (1, 1, 1)
    }
    volume = {n for n, m in head.named_modules() if isinstance(m, torch.nn.GroupNorm)}
    assert spatial == {"conv8.0", "conv8b.0", "post4.body.2"}
    assert volume == {"conv8.1", "conv8b.1", "post4.body.0", "post4.body.4"}


def test_gated_head_norms_nothing_over_the_half_volume() -> None:
    """The gated head is the dense head with the norm after the 1/2 conv fixed (no statistics over
    the conv's volume); the norm before it takes the up-sampled 1/4 rows' statistics, which the
    sparse graph has. That lets ``sparse`` compute 1/2 under the gated 1/4 voxels only, exactly."""
    head = build_head(dataclasses.replace(tiny_config(), head_kind="gated"))
    dense = build_head(tiny_config())
    volume = {
        n
        for n, m in head.named_modules()
        if isinstance(m, torch.nn.GroupNorm) and not isinstance(m, FixedGroupNorm)
    }
    assert volume == {"conv8.1", "post4.0", "post4.2.1", "post2.0"}  # 1/8, 1/4, the up-sampling
    assert {n for n, m in head.named_modules() if isinstance(m, FixedGroupNorm)} == {"post2.2.1"}
    head.load_state_dict(dense.state_dict())  # the same keys: a dense head's weights load


def test_gated_sparse_is_exact_where_the_half_grid_crops_children() -> None:
    """On an odd grid the 1/2 level crops the last children of the 1/4 level: they count neither in
    the first norm's statistics nor as neighbours (the dense conv's zero padding)."""
    torch.manual_seed(4)
    cfg = dataclasses.replace(tiny_config(), head_kind="gated", grid=ODD)
    head = build_head(cfg).eval()
    norm = head.fixed_norm()
    norm.fold(torch.rand(norm.num_groups) - 0.5, torch.rand(norm.num_groups) + 0.3)
    x = torch.randn(1, *bev_shape(cfg))
    with one_torch_thread(), torch.no_grad():
        occ, off = head.packed(x)
        s_occ, s_off, vox, _ = head.sparse(x, torch.zeros(1))
    assert head.cropped and vox.tolist() == list(range(occ[0, 0].numel()))
    torch.testing.assert_close(s_occ, occ.reshape(8, -1).t(), rtol=0, atol=1e-6)
    torch.testing.assert_close(s_off, off.reshape(8, 3, -1).permute(2, 0, 1), rtol=0, atol=1e-6)


def test_gated_sparse_skips_the_half_level_where_the_quarter_is_empty() -> None:
    """With a gate, 1/2 voxels are computed only under the 1/4 voxels above it: a 1/2 voxel whose
    parent fails the gate never appears, whatever its own occupancy."""
    torch.manual_seed(2)
    cfg = dataclasses.replace(tiny_config(), head_kind="gated")
    head = build_head(cfg).eval()
    x = torch.randn(1, *bev_shape(cfg))
    with torch.no_grad():
        (l4, _), (l2, _), _ = head.multi_scale(x)
        gate = torch.quantile(_gate_occupancy(head, x), 0.7).reshape(1)
        _, _, vox, _ = head.sparse(x, gate)
    h2, w2 = l2.shape[3:]
    occ4 = torch.sigmoid(l4)[0, 0]
    z, y, xx = vox // (h2 * w2), vox // w2 % h2, vox % w2
    assert len(vox) > 0 and torch.all(occ4[z // 2, y // 2, xx // 2] > gate)
    own = torch.sigmoid(l2)[0, 0].reshape(-1)
    assert int((own > gate).sum()) > len(vox)  # some voxels above the gate were never computed


@pytest.mark.parametrize("grid", [GRID_PRESETS["tiny"], ODD], ids=["tiny", "odd"])
def test_sparse_decoder_equals_packed_decoder(grid: GridConfig) -> None:
    rng = np.random.default_rng(1)
    half = packed_shape(grid)
    occ = rng.random((8, *half), dtype=np.float32)
    off = (rng.random((8, 3, *half), dtype=np.float32) - 0.5) * 0.1
    ref_pts, ref_conf = decode_packed(occ, off, grid, 0.7)
    rows_occ = occ.reshape(8, -1).T  # (N, 8)
    rows_off = off.reshape(8, 3, -1).transpose(2, 0, 1)  # (N, 8, 3)
    every = np.arange(rows_occ.shape[0])
    hit = np.flatnonzero((rows_occ > 0.7).any(axis=1))  # only the voxels with an occupied child
    for vox in (every, hit):
        pts, conf = decode_sparse(rows_occ[vox], rows_off[vox], vox, grid, 0.7)
        assert np.array_equal(pts, ref_pts) and np.array_equal(conf, ref_conf)
    fewer, _ = decode_sparse(rows_occ[hit[::2]], rows_off[hit[::2]], hit[::2], grid, 0.7)
    assert 0 < len(fewer) < len(ref_pts)
    assert {tuple(p) for p in fewer} <= {tuple(p) for p in ref_pts}  # a gate only removes points
    empty, _ = decode_sparse(np.zeros((0, 8)), np.zeros((0, 8, 3)), np.zeros(0, np.int64), grid, 0.5)
    assert empty.shape == (0, 3)
    with pytest.raises(ValueError, match="outside the half-scale grid"):
        decode_sparse(rows_occ[:1], rows_off[:1], np.array([every.size]), grid, 0.5)
    with pytest.raises(ValueError, match="sparse head output"):
        decode_sparse(rows_occ[:2], rows_off[:1], every[:2], grid, 0.5)


@pytest.fixture(scope="module", params=["dense", "sparse", "gated"])
def sparse_pipe(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Pipeline:
    """The coarse-to-fine graph of each head kind (ReconHead.sparse, SparseReconHead.sparse,
    GatedReconHead.sparse)."""
    folder = make_artifact(tmp_path_factory.mktemp("sparse"), "student", head_kind=request.param)
    return Pipeline.from_dir(folder, threads=1)


def _scan(pipe: Pipeline, n: int = 200) -> np.ndarray:
    rng = np.random.default_rng(3)
    lo, hi = np.asarray(pipe.artifact.grid.point_range[:3]), np.asarray(pipe.artifact.grid.point_range[3:])
    pts = np.zeros((n, len(pipe.columns)), np.float32)
    pts[:, :3] = lo + (hi - lo) * rng.random((n, 3))
    return pts


def test_keep_all_gate_decodes_the_dense_points(sparse_pipe: Pipeline) -> None:
    pipe, scan = sparse_pipe, _scan(sparse_pipe)
    assert pipe.artifact.gate is None and pipe.gate is None  # not calibrated: the dense head
    pipe.gate = 0.0
    try:
        occ, gate_occ = _sparse_outputs(pipe, scan)
        # a threshold no child of the lowest-gate voxels passes (random weights: no relation between
        # a voxel's own and its children's occupancy), so keeping every point needs fewer voxels
        for share in (0.5, 0.2, 0.1, 0.05, 0.02):
            thr = float(np.nextafter(occ[gate_occ <= np.quantile(gate_occ, share)].max(), np.float32(1)))
            if (occ > thr).sum() > 0:
                break
        every = pipe(scan, threshold=thr, steps=4)
        gate = keep_all_gate(occ, gate_occ, thr)
        pipe.gate = gate
        kept = pipe(scan, threshold=thr, steps=4)
        pipe.gate = float(np.quantile(gate_occ[gate_occ > gate], 0.5))  # above the keep-all gate
        gated = pipe(scan, threshold=thr, steps=4)
    finally:
        pipe.gate = None
    dense = pipe(scan, threshold=thr, steps=4)
    assert pipe.sparse_head_outputs() == {}  # the last call ran the dense head
    assert len(dense.points) > 0 and dense.stats["head_voxels"] == every.stats["head_voxels"]
    for res in (every, kept):
        if pipe.artifact.manifest["config"]["head_kind"] == "gated":  # gather + matmul:
            assert res.points.shape == dense.points.shape  # the same sums in another order
            np.testing.assert_allclose(res.points, dense.points, rtol=0, atol=1e-5)
            np.testing.assert_allclose(res.confidence, dense.confidence, rtol=0, atol=1e-6)
            continue
        assert np.array_equal(res.points, dense.points) and np.array_equal(res.confidence, dense.confidence)
    assert kept.stats["head_voxels"] < every.stats["head_voxels"]
    assert gated.stats["head_voxels"] < kept.stats["head_voxels"] and len(gated.points) < len(dense.points)
    near = np.abs(gated.points[:, None, :] - dense.points[None, :, :]).max(axis=2).min(axis=1)
    assert np.all(near <= 1e-5)  # a gate only removes points (gated head: same sums, other order)


def test_a_gate_nothing_passes_gives_an_empty_cloud(sparse_pipe: Pipeline) -> None:
    """No voxel above the gate (at 1/4 for the gated head): zero rows through every matmul and
    reshape of the graph, an empty cloud, no error."""
    sparse_pipe.gate = float(np.nextafter(np.float32(1.0), np.float32(0.0)))
    try:
        res = sparse_pipe(_scan(sparse_pipe), steps=2)
    finally:
        sparse_pipe.gate = None
    assert res.points.shape == (0, 3) and res.stats["head_voxels"] == 0


def _sparse_outputs(pipe: Pipeline, scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(children occupancy (N, 8), gate occupancy (N,)) of every half-scale voxel (gate 0)."""
    pipe(scan, steps=4)
    out = pipe.sparse_head_outputs()
    return out["occupancy"], out["gate_occupancy"]


def test_gate_in_the_manifest(sparse_pipe: Pipeline, tmp_path) -> None:
    folder = tmp_path / "m"
    shutil.copytree(sparse_pipe.artifact.root, folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    write_manifest(folder, {**manifest, "gate": 0.25})
    assert load_artifact(folder).gate == 0.25 and Pipeline.from_dir(folder).gate == 0.25
    for bad in (1.0, -0.1, "x"):
        write_manifest(folder, {**manifest, "gate": bad})
        with pytest.raises(MsdnetError, match="gate"):
            load_artifact(folder)
    graphs = [g for g in manifest["graphs"] if g["file"] != "recon_head_sparse.onnx"]
    write_manifest(folder, {**manifest, "graphs": graphs, "gate": None})
    assert load_artifact(folder).gate is None  # older artifacts: no sparse graph, dense head
    write_manifest(folder, {**manifest, "graphs": graphs, "gate": 0.2})
    with pytest.raises(MsdnetError, match="needs recon_head_sparse.onnx"):
        load_artifact(folder)


def test_keep_all_gate() -> None:
    occ = np.array([[0.9, 0, 0, 0, 0, 0, 0, 0], [0.1] * 8, [0.6] * 8], np.float32)
    gate_occ = np.array([0.3, 0.05, 0.8], np.float32)
    g = keep_all_gate(occ, gate_occ, 0.5)
    assert 0.0 <= g < 0.3 and np.all((gate_occ > g) >= (occ > 0.5).any(axis=1))
    assert keep_all_gate(occ[:0], gate_occ[:0], 0.5) == 0.0


def test_calibrate_gate_keeps_the_asked_share(sparse_pipe: Pipeline) -> None:
    scans = [_scan(sparse_pipe, 150), _scan(sparse_pipe, 250)]
    sparse_pipe.gate = 0.0
    try:  # a threshold 10 % of the children pass (random weights: 0.6 may pass none)
        thr = float(np.quantile(_sparse_outputs(sparse_pipe, scans[0])[0], 0.9))
    finally:
        sparse_pipe.gate = None
    full = calibrate_gate(sparse_pipe, scans, threshold=thr, recall=1.0)
    half = calibrate_gate(sparse_pipe, scans, threshold=thr, recall=0.5)
    assert sparse_pipe.gate is None  # left as it was
    assert full.points_kept == 1.0 and full.gate <= full.keep_all_gate + 1e-4 and full.frames == 2
    assert 0.5 <= half.points_kept < 1.0 and half.gate > full.gate and half.voxels_kept < full.voxels_kept
    with pytest.raises(MsdnetError, match="recall"):
        calibrate_gate(sparse_pipe, scans, recall=0.0)
