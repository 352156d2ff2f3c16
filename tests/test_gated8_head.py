"""The gated8 head: only the 1/8 and up-sampled 1/8 norms over a volume, the 1/8 gate grown by one
1/8 voxel (a neighbour of a passing voxel is computed), the 1/4 level skipped far from the passing
1/8 voxels, exact where it computes (parity at gate 0 is in test_sparse_head.py)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from export_helpers import one_torch_thread, tiny_config

from msdnet.runtime.spec.grid import GRID_PRESETS, GridConfig
from msdnet.training.models.assembly import bev_shape
from msdnet.training.nn.head_gated import FixedGroupNorm
from msdnet.training.nn.head_gated8 import Gated8ReconHead, near_occupancy
from msdnet.training.nn.heads import build_head

ODD = GridConfig((0.0, 0.0, 0.0, 7.0, 6.6, 3.3), (0.2, 0.2, 0.3))  # 35 x 33 x 11: both up-samplings crop


def _head(seed: int, grid: GridConfig | None = None) -> Gated8ReconHead:
    """A tiny gated8 head, its fixed norms folded with random statistics, whose 1/4 and 1/2 gates
    pass nearly everything (so the 1/8 gate decides)."""
    torch.manual_seed(seed)
    cfg = dataclasses.replace(tiny_config(), head_kind="gated8")
    if grid is not None:
        cfg = dataclasses.replace(cfg, grid=grid)
    head = build_head(cfg).eval()
    assert isinstance(head, Gated8ReconHead)
    for norm in head.fixed_norms():
        norm.fold(torch.rand(norm.num_groups) - 0.5, torch.rand(norm.num_groups) * 2 + 0.2)
    with torch.no_grad():
        head.occ[0].bias.fill_(6.0)
        head.occ[1].bias.fill_(6.0)
    return head


def _grandparents(vox: torch.Tensor, half: tuple[int, int, int], eighth: tuple[int, int, int]) -> set[int]:
    """Linear 1/8 indices of the 1/8 ancestors of half-scale voxels vox (N,)."""
    _, h2, w2 = half
    _, h8, w8 = eighth
    z, y, x = vox // (h2 * w2), vox // w2 % h2, vox % w2
    return set(((z // 4 * h8 + y // 4) * w8 + x // 4).tolist())


def test_gated8_head_norms_nothing_over_a_volume_below_the_eighth() -> None:
    """The only volume norms are the 1/8 conv's and the one on the up-sampled 1/8 volume (dense in
    the sparse graph: 1/8 is small); every norm after them is fixed. A dense or gated head's
    weights load (all but the 1/8 gate)."""
    head = build_head(dataclasses.replace(tiny_config(), head_kind="gated8"))
    volume = {
        n
        for n, m in head.named_modules()
        if isinstance(m, torch.nn.GroupNorm) and not isinstance(m, FixedGroupNorm)
    }
    assert volume == {"conv8.1", "post4.0"}
    fixed = {n for n, m in head.named_modules() if isinstance(m, FixedGroupNorm)}
    assert fixed == {"post4.2.1", "post2.0", "post2.2.1"}
    for source in ("dense", "gated"):
        other = build_head(dataclasses.replace(tiny_config(), head_kind=source))
        missing, unexpected = head.load_state_dict(other.state_dict(), strict=False)
        assert missing == ["occ8.weight", "occ8.bias"] and not unexpected


def test_near_occupancy_is_the_passing_set_grown_by_one_voxel() -> None:
    occ = torch.zeros(1, 1, 4, 5, 6)
    occ[0, 0, 1, 2, 3] = 0.9
    occ[0, 0, 3, 4, 5] = 0.4  # a corner: its neighbourhood is clipped by the volume
    near = near_occupancy(occ)[0, 0]
    grown = torch.zeros(4, 5, 6, dtype=torch.bool)
    grown[0:3, 1:4, 2:5] = True
    assert torch.equal(near > 0.5, grown)
    # the corner's 2 x 2 x 2 share (2, 3, 4) with the first block, where the larger value holds
    assert int((near > 0.3).sum()) == 27 + 7 and near[2, 3, 4] == pytest.approx(0.9)


def test_the_eighth_gate_keeps_the_neighbours_of_a_passing_voxel() -> None:
    """One 1/8 voxel above the gate: the coarse-to-fine graph still decodes under all its 3x3x3
    neighbours (whose own 1/8 occupancy is below the gate), and under nothing farther."""
    head = _head(3)
    x = torch.randn(1, *bev_shape(tiny_config()))
    with one_torch_thread(), torch.no_grad():
        occ8 = torch.sigmoid(head.occ8(head._eighth(x)))[0, 0]  # (D8, H8, W8)
        top = occ8.reshape(-1).topk(2).values
        gate = ((top[0] + top[1]) / 2).reshape(1)  # only the largest passes by itself
        _, _, vox, g = head.sparse(x, gate)
        near8 = head.gate_volumes(x)[0]
    eighth, half = tuple(occ8.shape), head.shapes[1]
    best = int(occ8.reshape(-1).argmax())
    d8, h8, w8 = eighth
    bz, by, bx = best // (h8 * w8), best // w8 % h8, best % w8
    block = {
        (z * h8 + y) * w8 + xx
        for z in range(max(bz - 1, 0), min(bz + 2, d8))
        for y in range(max(by - 1, 0), min(by + 2, h8))
        for xx in range(max(bx - 1, 0), min(bx + 2, w8))
    }
    assert int((occ8 > gate).sum()) == 1 and len(block) > 1
    assert _grandparents(vox, half, eighth) == block  # every neighbour decoded, nothing beyond
    assert set(torch.nonzero(near8.reshape(-1) > gate).reshape(-1).tolist()) == block
    assert torch.all(g > gate)


@pytest.mark.parametrize("grid", [GRID_PRESETS["tiny"], ODD], ids=["tiny", "odd"])
def test_gated8_sparse_skips_the_quarter_level_far_from_the_eighth(grid: GridConfig) -> None:
    """With a gate, a kept 1/2 voxel's 1/8 grandparent has a neighbour (or itself) above the gate;
    some voxels are skipped; where it computes, the values are the dense ones (on an odd grid too,
    where both up-samplings crop)."""
    head = _head(5, grid)
    cfg = dataclasses.replace(tiny_config(), head_kind="gated8", grid=grid)
    x = torch.randn(1, *bev_shape(cfg))
    with one_torch_thread(), torch.no_grad():
        occ, off = head.packed(x)
        near8 = head.gate_volumes(x)[0]
        gate = torch.quantile(near8.reshape(-1), 0.6).reshape(1)
        s_occ, s_off, vox, g = head.sparse(x, gate)
    h2, w2 = occ.shape[3:]
    z, y, xx = vox // (h2 * w2), vox // w2 % h2, vox % w2
    assert len(vox) > 0 and torch.all(near8[z // 4, y // 4, xx // 4] > gate) and torch.all(g > gate)
    assert len(vox) < occ[0, 0].numel()
    torch.testing.assert_close(s_occ, occ.reshape(8, -1).t()[vox], rtol=0, atol=1e-6)
    torch.testing.assert_close(s_off, off.reshape(8, 3, -1).permute(2, 0, 1)[vox], rtol=0, atol=1e-6)
