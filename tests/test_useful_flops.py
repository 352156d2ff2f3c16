"""Useful FLOPs (benchmarks/latency/useful): the FLOPs on occupied voxels only, against counts by
hand on the tiny model."""

from __future__ import annotations

import numpy as np
import pytest
from export_helpers import make_artifact

from msdnet.benchmarks.flops import graph_flops, node_flops
from msdnet.benchmarks.latency.timing import synthetic_radar
from msdnet.benchmarks.latency.useful import efficiency, occupied_share, stage_flops, voxel_mask
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.model import onnx_spec


@pytest.fixture(scope="module")
def pipe(tmp_path_factory) -> Pipeline:
    return Pipeline.from_dir(make_artifact(tmp_path_factory.mktemp("art"), "student"), threads=1)


def test_occupied_share_by_hand():
    mask = np.zeros((4, 8, 8), bool)
    mask[0, 0, 0] = mask[3, 7, 7] = mask[1, 0, 1] = True
    assert occupied_share(mask, (4, 8, 8)) == 3 / 256
    assert occupied_share(mask, (2, 4, 4)) == 2 / 32  # (0,0,0) and (1,0,1) share a cell
    assert occupied_share(mask, (8, 8)) == 3 / 64  # a BEV map: z collapsed
    assert occupied_share(mask, (4, 4)) == 2 / 16
    assert occupied_share(np.zeros((4, 8, 8), bool), (2, 2)) == 0.0


def test_voxel_mask_drops_points_outside_the_grid(pipe):
    grid = pipe.artifact.grid
    lo, hi = np.asarray(grid.point_range[:3]), np.asarray(grid.point_range[3:])
    pts = np.stack([lo + 1e-3, hi + 1.0, (lo + hi) / 2])
    mask = voxel_mask(grid, pts)
    assert mask.shape == tuple(grid.shape_zyx) and mask.sum() == 2 and mask[0, 0, 0]


def test_encoder_useful_flops_are_the_real_rulebook_pairs(pipe):
    """A rulebook-fed matmul's useful FLOPs: 2 x real entries x C_in x C_out."""
    pts = synthetic_radar(pipe.columns, pipe.artifact.grid, 300, seed=3)
    feeds, _, _ = pipe.encoder_feeds(pipe.select_columns(pts))
    nodes = node_flops(pipe.artifact.root / onnx_spec.ENCODER.file, {k: v.shape for k, v in feeds.items()})
    fed = [n for n in nodes if n.rules is not None]
    assert {n.rules for n in fed} == {k for k in feeds if "_rules_" in k}
    by_hand = 0.0
    for n in fed:
        rules = feeds[n.rules]
        level = int(n.rules.rsplit("_", 1)[1])
        n_in = len(feeds[f"subm_rules_{level - 1}"]) if n.rules.startswith("down") else len(rules)
        c_out = n.out_shape[-1]
        c_in = n.flops // (2 * rules.size * c_out)  # the dense gather form: every tap
        by_hand += 2 * int((rules < n_in).sum()) * c_in * c_out
    rest = sum(n.flops for n in nodes if n.rules is None and n.op == "Gemm")  # the VFE, every voxel
    enc = stage_flops(pipe, pts, pipe.artifact.threshold)["encoder"]
    bev = [n for n in nodes if n.op == "Conv"]  # the BEV conv: only cells under an input voxel
    assert enc["gflop"] * 1e9 == pytest.approx(sum(n.flops for n in nodes))
    assert by_hand + rest <= enc["gflop_useful"] * 1e9 <= by_hand + rest + sum(n.flops for n in bev)
    assert enc["useful_share"] < 1


def test_every_stage_and_the_efficiency(pipe):
    pts = synthetic_radar(pipe.columns, pipe.artifact.grid, 300, seed=3)
    flops = stage_flops(pipe, pts, pipe.artifact.threshold)
    assert set(flops) == {"encoder", "rgfd_adapter", "ddim_loop", "recon_head"}
    calls = pipe.coefficients().shape[0]
    bev = pipe.bev_shape
    step = graph_flops(pipe.artifact.root / onnx_spec.DENOISER_STEP.file, {"x_t": bev, "t": (1,)})
    assert flops["ddim_loop"]["gflop"] * 1e9 == pytest.approx(calls * step)
    for row in flops.values():
        assert 0 < row["gflop_useful"] <= row["gflop"]
    stages = {k: {"median": 2.0} for k in flops}
    eff = efficiency(flops, stages, sgemm_gflops=100.0)
    assert eff["encoder"]["efficiency"] == pytest.approx(flops["encoder"]["gflop_useful"] / 2e-3 / 100)
    assert eff["graphs"]["ms"] == 8.0
