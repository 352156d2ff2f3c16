"""The full scale of Eq. 5-6 on sparse rows (training/models/full_rows.py): exact at rate 1,
unbiased below it, and what it keeps."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msdnet.training.config import MODEL_PRESETS
from msdnet.training.data.targets import make_targets
from msdnet.training.models.full_rows import select_rows
from msdnet.training.models.losses import head_loss, reconstruction_loss
from msdnet.training.nn.heads import build_head

EXACT = 1e-5  # relative: the rows form sums the same terms in another order
GRAD = 1e-4  # largest gradient difference relative to the largest gradient element
MEAN_OF_DRAWS = 0.03  # relative: 100 draws at rate 0.2 around the exact loss


def _setup(kind: str = "dense", pos_weight: float = 20.0):
    cfg = MODEL_PRESETS["tiny"]
    cfg = dataclasses.replace(
        cfg, head_kind=kind, losses=dataclasses.replace(cfg.losses, occ_pos_weight=pos_weight)
    )
    torch.manual_seed(0)
    head = build_head(cfg)
    rng = np.random.default_rng(0)
    lo, hi = np.array(cfg.grid.point_range[:3]), np.array(cfg.grid.point_range[3:])
    clouds = []
    for _ in range(2):  # a wall and scattered points: occupied voxels beside empty regions
        wall = np.stack([np.full(300, 8.0), rng.uniform(-4, 4, 300), rng.uniform(-1.5, 3, 300)], 1)
        scatter = rng.uniform(lo, hi, (80, 3))
        clouds.append(np.concatenate([wall, scatter]).astype(np.float32))
    targets = make_targets(clouds, cfg.grid)
    h8, w8 = cfg.grid.shape_zyx[1] // 8, cfg.grid.shape_zyx[2] // 8
    features = torch.randn(2, cfg.bev_channels, h8, w8)
    return cfg, head, features, targets


@pytest.mark.parametrize("kind", ["dense", "sparse"])
def test_rate_one_is_the_dense_loss_and_gradient(kind):
    cfg, head, features, targets = _setup(kind)
    dense = reconstruction_loss(head.multi_scale(features), targets, cfg.losses)
    dense["recon"].backward()
    g_dense = [p.grad.clone() for p in head.parameters()]
    head.zero_grad()
    rows = select_rows(targets, 1.0)
    assert len(rows.index) == targets[1][0].numel()  # every half-scale voxel
    sparse = reconstruction_loss(head.multi_scale(features, rows.index), targets, cfg.losses, rows)
    sparse["recon"].backward()
    for name in ("occ_s1", "off_s1", "recon"):
        assert torch.allclose(sparse[name], dense[name], rtol=EXACT), (name, sparse[name], dense[name])
    for g, p in zip(g_dense, head.parameters(), strict=True):
        err = float((p.grad - g).abs().max() / g.abs().max().clamp_min(1e-12))
        assert err < GRAD, err


def test_sampled_rows_keep_every_occupied_voxel_and_are_unbiased():
    cfg, head, features, targets = _setup()
    with torch.no_grad():
        dense = reconstruction_loss(head.multi_scale(features), targets, cfg.losses)
        torch.manual_seed(1)
        x4, x2 = head._trunk(features)  # the draws differ at the full scale only
        coarse = [head._branches(x4, 0), head._branches(x2, 1)]
        occ, off, kept = [], [], []
        for _ in range(100):
            rows = select_rows(targets, 0.2)
            assert float(rows.occ.sum()) == float(targets[2][0].sum())  # no occupied voxel dropped
            preds = [*coarse, head._full_or_rows(x2, rows.index)]
            out = reconstruction_loss(preds, targets, cfg.losses, rows)
            occ.append(float(out["occ_s1"]))
            off.append(float(out["off_s1"]))
            kept.append(len(rows.index) / targets[1][0].numel())
    assert float(np.mean(occ)) == pytest.approx(float(dense["occ_s1"]), rel=MEAN_OF_DRAWS)
    assert off == pytest.approx([float(dense["off_s1"])] * len(off), rel=EXACT)  # all occupied: exact
    assert np.std(occ) > 0 and 0.2 < np.mean(kept) < 0.9  # a draw, and fewer voxels than dense


def test_head_loss_is_exact_outside_training():
    cfg, head, features, targets = _setup()
    cfg = dataclasses.replace(cfg, losses=dataclasses.replace(cfg.losses, full_scale_rate=0.05))
    with torch.no_grad():
        dense = reconstruction_loss(head.multi_scale(features), targets, cfg.losses)
        assert torch.equal(head_loss(head, features, targets, cfg.losses, False)["recon"], dense["recon"])
        sampled = head_loss(head, features, targets, cfg.losses, True)["recon"]
    assert not torch.equal(sampled, dense["recon"])


def test_rate_outside_zero_one_refused():
    _, _, _, targets = _setup()
    with pytest.raises(ValueError, match="rate"):
        select_rows(targets, 0.0)
