"""Rulebook sparse convolution equals dense conv3d; the sparse encoder exports to ONNX."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from msdnet.runtime.engine.rulebook import build_encoder_rulebooks
from msdnet.runtime.model.onnx_spec import ENCODER, OPSET
from msdnet.training.config import MODEL_PRESETS
from msdnet.training.data.batch import make_encoder_input
from msdnet.training.nn.encoder import SparseEncoder, level_shapes
from msdnet.training.nn.sparse import SparseDownConv3d, SubMConv3d

SHAPE = (5, 7, 6)  # (D, H, W): odd sizes exercise the stride-2 border


def _random_voxels(rng: np.random.Generator, batch: int, n: int) -> np.ndarray:
    """(V, 4) int32 [b, z, y, x], unique, sorted by (b, linear index)."""
    cells = int(np.prod(SHAPE))
    parts = []
    for b in range(batch):
        lin = np.sort(rng.choice(cells, size=n, replace=False))
        zyx = np.stack(np.unravel_index(lin, SHAPE), axis=1)
        parts.append(np.concatenate([np.full((n, 1), b), zyx], axis=1))
    return np.concatenate(parts).astype(np.int32)


def _densify(feats: torch.Tensor, coords: np.ndarray, batch: int, shape) -> torch.Tensor:
    """(V, C) at coords [b, z, y, x] -> (B, C, D, H, W) zeros elsewhere."""
    dense = feats.new_zeros(batch, feats.shape[1], *shape)
    c = torch.from_numpy(coords.astype(np.int64))
    dense[c[:, 0], :, c[:, 1], c[:, 2], c[:, 3]] = feats
    return dense


def _at(dense: torch.Tensor, coords: np.ndarray) -> torch.Tensor:
    """(B, C, D, H, W) read at coords (V, 4) -> (V, C)."""
    c = torch.from_numpy(coords.astype(np.int64))
    return dense[c[:, 0], :, c[:, 1], c[:, 2], c[:, 3]]


def test_subm_and_down_equal_dense_masked_conv3d():
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    batch, cin, cout = 2, 3, 4
    coords = _random_voxels(rng, batch, 60)
    rb = build_encoder_rulebooks(coords, SHAPE, num_down=1)
    feats = torch.randn(coords.shape[0], cin, dtype=torch.float64)
    dense_in = _densify(feats, coords, batch, SHAPE)

    subm = SubMConv3d(cin, cout).double()
    torch.nn.init.normal_(subm.bias)
    got = subm(feats, torch.from_numpy(rb.subm[0].astype(np.int64)))
    ref = F.conv3d(dense_in, subm.dense_weight(), subm.bias, stride=1, padding=1)
    torch.testing.assert_close(got, _at(ref, coords), rtol=1e-10, atol=1e-10)

    down = SparseDownConv3d(cin, cout).double()
    torch.nn.init.normal_(down.bias)
    out_coords = rb.coords[1]
    got = down(feats, torch.from_numpy(rb.down[0].astype(np.int64)))
    ref = F.conv3d(dense_in, down.dense_weight(), down.bias, stride=2, padding=1)
    assert ref.shape[2:] == rb.shapes[1]
    torch.testing.assert_close(got, _at(ref, out_coords), rtol=1e-10, atol=1e-10)
    # Every dense output with any input in its window is an output site: elsewhere only bias.
    ref_nobias = F.conv3d(dense_in, down.dense_weight(), None, stride=2, padding=1)
    site = torch.zeros(ref.shape[0], *ref.shape[2:], dtype=torch.bool)
    oc = torch.from_numpy(out_coords.astype(np.int64))
    site[oc[:, 0], oc[:, 1], oc[:, 2], oc[:, 3]] = True
    assert torch.all(ref_nobias.permute(0, 2, 3, 4, 1)[~site] == 0)
    assert 0 < oc.shape[0] < site.numel()


def _cloud(rng: np.random.Generator, n: int, cfg) -> np.ndarray:
    """(n, len(radar_columns)) float32 points inside the grid."""
    lo = np.asarray(cfg.grid.point_range[:3])
    hi = np.asarray(cfg.grid.point_range[3:])
    xyz = lo + rng.random((n, 3)) * (hi - lo)
    extra = rng.normal(size=(n, len(cfg.radar_columns) - 3))
    return np.concatenate([xyz, extra], axis=1).astype(np.float32)


def test_encoder_shapes_and_empty_cloud():
    cfg = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    enc = SparseEncoder(cfg, "radar").eval()
    rng = np.random.default_rng(1)
    empty = np.zeros((0, len(cfg.radar_columns)), np.float32)
    inp = make_encoder_input([_cloud(rng, 200, cfg), empty], cfg.grid, cfg.max_voxels_radar)
    d8, h8, w8 = level_shapes(cfg.grid)[-1]
    assert inp.features.shape[1] == len(cfg.radar_columns)
    assert int(inp.bev_coords[:, 0].max()) == 0  # sample 1 has no voxel
    with torch.no_grad():
        out = enc.encode(inp)
        alone = enc.encode(make_encoder_input([empty], cfg.grid, cfg.max_voxels_radar))
    assert out.shape == (2, cfg.bev_channels, h8, w8)
    # The empty sample is the encoder of nothing: the 1x1 conv's bias everywhere.
    torch.testing.assert_close(out[1:], alone)
    assert not torch.allclose(out[0], out[1])


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # the TorchScript exporter (dynamo=False)
def test_encoder_onnx_matches_torch_on_other_voxel_count(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    cfg = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    enc = SparseEncoder(cfg, "radar").eval()
    rng = np.random.default_rng(2)
    traced = make_encoder_input([_cloud(rng, 300, cfg)], cfg.grid, cfg.max_voxels_radar)
    other = make_encoder_input([_cloud(rng, 90, cfg)], cfg.grid, cfg.max_voxels_radar)
    assert other.features.shape[0] != traced.features.shape[0]
    path = tmp_path / "encoder.onnx"
    torch.onnx.export(
        enc,
        traced.tensors(),
        str(path),
        input_names=list(ENCODER.inputs),
        output_names=list(ENCODER.outputs),
        dynamic_axes=ENCODER.dynamic_axes,
        opset_version=OPSET,
        dynamo=False,
    )
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {n: t.numpy() for n, t in zip(ENCODER.inputs, other.tensors(), strict=True)}
    got = sess.run(None, feeds)[0]
    with torch.no_grad():
        want = enc.encode(other).numpy()
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
