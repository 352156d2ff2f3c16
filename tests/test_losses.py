"""Every loss term and the ground-truth targets on hand-made cases computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from msdnet.runtime.spec.grid import GridConfig
from msdnet.training.config import LossWeights
from msdnet.training.data.targets import scale_shapes, voxel_targets
from msdnet.training.models.losses import (
    eps_loss,
    feature_distillation,
    occupancy_bce,
    offset_l1,
    reconstruction_loss,
    student_total,
)


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def test_occupancy_bce_eq5():
    probs = [0.8, 0.3, 0.5, 0.9]
    target = torch.tensor([1.0, 0.0, 1.0, 0.0]).reshape(1, 1, 2, 2)
    logits = torch.tensor([_logit(p) for p in probs]).reshape(1, 1, 2, 2)
    want = -(math.log(0.8) + math.log(0.7) + math.log(0.5) + math.log(0.1)) / 4
    assert occupancy_bce(logits, target).item() == pytest.approx(want, rel=1e-6)
    # occupied voxels (0.8 and 0.5 here) weighted 3x
    want_w = -(3 * math.log(0.8) + math.log(0.7) + 3 * math.log(0.5) + math.log(0.1)) / 4
    assert occupancy_bce(logits, target, 3.0).item() == pytest.approx(want_w, rel=1e-6)


def test_offset_l1_eq6_only_occupied_voxels():
    occ = torch.tensor([1.0, 0.0, 1.0]).reshape(1, 1, 1, 3)  # (B, D, H, W)
    pred = torch.tensor([[0.1, 9.0, 0.0], [-0.2, 9.0, 0.0], [0.05, 9.0, 0.0]]).reshape(1, 3, 1, 1, 3)
    tgt = torch.tensor([[0.0, 0.0, 0.1], [0.1, 0.0, 0.0], [0.05, 0.0, -0.1]]).reshape(1, 3, 1, 1, 3)
    # voxel 0: |0.1| + |-0.3| + 0 = 0.4; voxel 2: 0.1 + 0 + 0.1 = 0.2; voxel 1 (empty) ignored.
    assert offset_l1(pred, tgt, occ).item() == pytest.approx((0.4 + 0.2) / 2, rel=1e-6)
    none = torch.zeros_like(occ)
    assert offset_l1(pred, tgt, none).item() == 0.0


def test_reconstruction_loss_eq7_weights_scales():
    w = LossWeights(rho=1.0, zeta=10.0)
    preds, targets, want = [], [], 0.0
    for s, p in enumerate([0.25, 0.5, 0.75]):
        logits = torch.full((1, 1, 1, 1, 2), _logit(p))
        occ = torch.tensor([[[[1.0, 0.0]]]])  # (1, 1, 1, 2)
        off = torch.zeros(1, 3, 1, 1, 2)
        off[0, 0, 0, 0, 0] = 0.1 * (s + 1)  # error only on the occupied voxel's x
        preds.append((logits, off))
        targets.append((occ, torch.zeros(1, 3, 1, 1, 2)))
        want += -(math.log(p) + math.log(1 - p)) / 2 + 10.0 * 0.1 * (s + 1)
    terms = reconstruction_loss(preds, targets, w)
    assert terms["recon"].item() == pytest.approx(want, rel=1e-6)
    assert terms["off_s1"].item() == pytest.approx(0.3, rel=1e-6)
    assert terms["occ_s2"].item() == pytest.approx(math.log(2.0), rel=1e-6)


def test_feature_distillation_eq8_eq14():
    teacher = torch.tensor([[3.0, 0.0, 0.0], [4.0, 0.0, 1.0]]).reshape(1, 2, 1, 3)  # (B, C, H, W)
    student = torch.zeros_like(teacher)
    nonempty = torch.tensor([[[True, False, False]]])  # (B, H, W)
    # cell norms 5, 0, 1: alpha * 5 + gamma * mean(0, 1)
    got = feature_distillation(student, teacher, nonempty, alpha=10.0, gamma=20.0)
    assert got.item() == pytest.approx(10 * 5 + 20 * 0.5, rel=1e-6)
    all_empty = torch.zeros_like(nonempty)
    got = feature_distillation(student, teacher, all_empty, alpha=10.0, gamma=20.0)
    assert got.item() == pytest.approx(20 * 2.0, rel=1e-6)
    # The gradient is finite where student == teacher (norm 0).
    s = teacher.clone().requires_grad_(True)
    feature_distillation(s, teacher, nonempty, 10.0, 20.0).backward()
    assert torch.isfinite(s.grad).all()


def test_eps_loss_eq10_and_student_total_eq15():
    assert eps_loss(torch.tensor([1.0, 2.0]), torch.tensor([0.0, 0.0])).item() == 2.5
    w = LossWeights(lambdas=(1.0, 0.01, 5.0, 10.0))
    one = torch.tensor(1.0)
    got = student_total(2 * one, 100 * one, 3 * one, 0.5 * one, w)
    assert got.item() == pytest.approx(2 + 1 + 15 + 5, rel=1e-6)


def test_voxel_targets_means_and_centres_per_scale():
    grid = GridConfig((0.0, 0.0, 0.0, 4.0, 4.0, 2.0), (1.0, 1.0, 1.0))  # (D, H, W) = (2, 4, 4)
    assert scale_shapes(grid) == [(1, 1, 1), (1, 2, 2), (2, 4, 4)]
    pts = np.array(
        [
            [0.2, 0.4, 0.5],  # full voxel (z0, y0, x0)
            [0.4, 0.6, 0.7],  # same voxel: mean (0.3, 0.5, 0.6)
            [1.5, 0.5, 1.5],  # voxel (z1, y0, x1): same 1/2 cell (0, 0, 0)
            [3.5, 3.5, 0.5],  # voxel (z0, y3, x3): 1/2 cell (0, 1, 1)
            [9.0, 0.0, 0.0],  # outside: ignored
        ],
        np.float32,
    )
    (occ4, off4), (occ2, off2), (occ1, off1) = voxel_targets(pts, grid)
    assert occ1.sum() == 3 and occ1[0, 0, 0] == 1 and occ1[1, 0, 1] == 1 and occ1[0, 3, 3] == 1
    np.testing.assert_allclose(off1[:, 0, 0, 0], [0.3 - 0.5, 0.5 - 0.5, 0.6 - 0.5], atol=1e-6)
    np.testing.assert_allclose(off1[:, 1, 0, 1], [0.0, 0.0, 0.0], atol=1e-6)
    assert np.all(off1[:, occ1 == 0] == 0)
    # 1/2 scale: voxels of 2 m; cell (0, 0, 0) holds the first three points, centre (1, 1, 1).
    assert occ2.sum() == 2 and occ2[0, 0, 0] == 1 and occ2[0, 1, 1] == 1
    mean = pts[:3].astype(np.float64).mean(axis=0)
    np.testing.assert_allclose(off2[:, 0, 0, 0], mean - 1.0, atol=1e-6)
    np.testing.assert_allclose(off2[:, 0, 1, 1], [3.5 - 3.0, 3.5 - 3.0, 0.5 - 1.0], atol=1e-6)
    # 1/4 scale: one 4 m cell (reaching past z = 2), centre (2, 2, 2).
    assert occ4.shape == (1, 1, 1) and occ4[0, 0, 0] == 1
    np.testing.assert_allclose(off4[:, 0, 0, 0], pts[:4].mean(axis=0) - 2.0, atol=1e-6)
    # An empty cloud gives all-empty targets of the same shapes.
    for (occ, off), shape in zip(
        voxel_targets(np.zeros((0, 3), np.float32), grid), scale_shapes(grid), strict=True
    ):
        assert occ.shape == shape and off.shape == (3, *shape) and not occ.any() and not off.any()
