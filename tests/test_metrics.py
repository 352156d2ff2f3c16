"""Metrics against cases computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msdnet.runtime.metrics import cloud as M

P = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
G = np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.3]])
# d(P -> G) = [0, 1];  d(G -> P) = [0, 2, 0.3]


def test_chamfer_by_hand():
    assert M.chamfer_distance(P, G) == pytest.approx(0.5 * (0.5 + 2.3 / 3))
    assert M.chamfer_distance(P, G, squared=True) == pytest.approx(0.5 * (0.5 + 4.09 / 3))
    assert M.chamfer_distance(P, P) == 0.0


def test_mhd_by_hand():
    assert M.modified_hausdorff(P, G) == pytest.approx(max(0.5, 2.3 / 3))


def test_fscore_by_hand():
    # t = 0.5: precision 1/2, recall 2/3 -> F = 2 * 1/2 * 2/3 / (7/6) = 4/7
    assert M.fscore(P, G, 0.5) == pytest.approx(4 / 7)
    # t = 0.05: precision 1/2, recall 1/3 -> F = 2/5
    assert M.fscore(P, G, 0.05) == pytest.approx(0.4)
    assert M.fscore(P + 10.0, G, 0.5) == 0.0


def test_empty_clouds():
    empty = np.zeros((0, 3))
    assert math.isnan(M.chamfer_distance(empty, G))
    assert math.isnan(M.modified_hausdorff(G, empty))
    assert M.fscore(empty, G, 0.1) == 0.0


def test_bev_histogram_and_jsd_by_hand():
    rng = (0.0, 0.0, 2.0, 2.0)  # 2 x 2 cells of 1 m
    a = M.bev_histogram(np.array([[0.5, 0.5, 0], [0.5, 0.5, 0], [1.5, 1.5, 0], [9, 9, 0]]), rng, 1.0)
    np.testing.assert_allclose(a, [[2 / 3, 0], [0, 1 / 3]])
    p = np.array([[1.0, 0.0]])
    q = np.array([[0.0, 1.0]])
    assert M.jsd(p, q) == pytest.approx(1.0)  # disjoint supports: 1 bit
    assert M.jsd(p, p) == pytest.approx(0.0)
    # P = (1/2, 1/2), Q = (1, 0): M = (3/4, 1/4)
    expected = 0.5 * (0.5 * math.log2(0.5 / 0.75) + 0.5 * math.log2(0.5 / 0.25)) + 0.5 * math.log2(1 / 0.75)
    assert M.jsd(np.array([[0.5, 0.5]]), np.array([[1.0, 0.0]])) == pytest.approx(expected)


def test_mmd_by_hand():
    # two cells 1 m apart, sigma 1 m: k(0) = 1, k(1) = exp(-1/2); P - Q = (1, -1)
    p, q = np.array([[1.0], [0.0]]), np.array([[0.0], [1.0]])
    assert M.mmd(p, q, bin_size=1.0, sigma=1.0) == pytest.approx(2 - 2 * math.exp(-0.5))
    assert M.mmd(p, p) == 0.0


def test_score_frame_collects_everything():
    s = M.score_frame(P, G, (-1.0, -1.0, 3.0, 3.0))
    assert s.cd == pytest.approx(M.chamfer_distance(P, G))
    assert set(s.fscore) == set(M.FSCORE_THRESHOLDS)
    assert s.num_points == 2 and 0 <= s.jsd <= 1 and s.mmd >= 0
