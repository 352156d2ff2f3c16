"""The R2LDM authors' metric formulas (runtime.metrics.official) on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msdnet.runtime.metrics.official import (
    official_bev_histogram,
    official_centroids,
    official_scores,
    official_set_scores,
)


def test_centroids_crop_half_open_and_average_per_cell():
    pts = np.array(
        [
            [0.01, 0.01, 0.01],  # cell (128, 128, 4) of the 0.125 m grid from (-16, -16, -0.5)
            [0.05, 0.05, 0.05],  # same cell: centroid (0.03, 0.03, 0.03)
            [1.00, 0.00, 0.00],  # a cell of its own
            [16.0, 0.00, 0.00],  # x = 16 is outside the half-open crop
            [0.00, 0.00, -0.6],  # below z = -0.5
            [np.nan, 0.0, 0.0],  # not finite
        ],
        np.float32,
    )
    out = official_centroids(pts)
    assert out.shape == (2, 3)
    np.testing.assert_allclose(sorted(out[:, 0].tolist()), [0.03, 1.0], atol=1e-6)
    np.testing.assert_allclose(out[np.argmin(out[:, 0])], [0.03, 0.03, 0.03], atol=1e-6)


def test_squared_chamfer_is_a_sum_and_hausdorff_is_the_squared_max():
    pred = np.array([[0.0, 0.0, 0.0]], np.float32)
    gt = np.array([[0.0, 0.0, 0.0], [0.3, 0.4, 0.0]], np.float32)  # 0.5 m away: d^2 = 0.25
    s = official_scores(pred, gt, preprocess=False)
    # pred -> gt: [0]; gt -> pred: [0, 0.25]; CD = 0 + 0.125 (a sum of the means, not their average)
    assert s["chamfer_squared_l2"] == pytest.approx(0.125, rel=1e-6)
    assert s["hausdorff_squared_l2"] == pytest.approx(0.25, rel=1e-6)
    assert s["precision"] == 1.0 and s["recall"] == 0.5
    assert s["fscore"] == pytest.approx(2 * 0.5 / 1.5, rel=1e-6)
    assert s["valid"] == 1.0


def test_fscore_counts_points_within_five_centimetres():
    pred = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], np.float32)
    gt = np.array([[0.04, 0.0, 0.0], [1.06, 0.0, 0.0]], np.float32)  # 4 cm in, 6 cm out
    s = official_scores(pred, gt, preprocess=False)
    assert s["precision"] == 0.5 and s["recall"] == 0.5
    assert s["chamfer_squared_l2"] == pytest.approx((0.04**2 + 0.06**2) / 2 * 2, rel=1e-4)


def test_empty_prediction_is_not_a_valid_pair():
    s = official_scores(np.empty((0, 3), np.float32), np.ones((3, 3), np.float32))
    assert s["valid"] == 0.0 and math.isnan(s["chamfer_squared_l2"])


def test_bev_histogram_bins_and_depth_window():
    pts = np.array([[5.0, 0.0, 0.0], [1.0, 0.0, 0.0], [75.0, 0.0, 0.0], [5.0, 0.1, 0.0]])
    h = official_bev_histogram(pts)
    assert h.shape == (100, 100) and h.sum() == 2  # 1 m is nearer than 3 m, 75 m beyond 70 m
    assert h[53, 50] == 2  # x: (5 + 80) / 1.6 = 53.1, y: 80 / 1.6 = 50


def test_set_scores_hand_values():
    a = np.zeros((100, 100))
    a[10, 10] = 3
    b = np.zeros((100, 100))
    b[20, 20] = 1
    same = official_set_scores([a, b], [a.copy(), b.copy()])
    assert same["jsd"] == pytest.approx(0.0, abs=1e-12)
    assert same["mmd"] == pytest.approx(0.0, abs=1e-12)
    apart = official_set_scores([a], [b])
    # disjoint distributions: JS divergence ln 2, distance sqrt(ln 2); MMD 1 + 1 - 2 exp(-2 / (2 * 0.25))
    assert apart["jsd"] == pytest.approx(math.sqrt(math.log(2)), rel=1e-9)
    assert apart["mmd"] == pytest.approx(2 - 2 * math.exp(-4.0), rel=1e-9)
    skipped = official_set_scores([a, np.zeros((100, 100))], [b, b])
    assert skipped["valid_pairs"] == 1.0 and skipped["jsd"] == pytest.approx(apart["jsd"])


class _Row:
    """A stand-in method row: name, role and backend are all margins_each reads."""

    def __init__(self, name: str, role: str) -> None:
        self.name, self.role, self.backend = name, role, "onnxruntime"


def test_margins_over_every_r2ldm_row():
    from msdnet.benchmarks.quality.official import OFFICIAL_KEYS, margins_each

    rows = [_Row("MSDNet", "msdnet"), _Row("R2LDM as published", "r2ldm"), _Row("R2LDM", "r2ldm")]
    base = {"hausdorff_squared_l2": 1.0, "fscore": 0.5, "jsd": 0.2}
    summary = {
        "MSDNet": {**base, "chamfer_squared_l2": 0.85},
        "R2LDM as published": {**base, "chamfer_squared_l2": 1.0},
        "R2LDM": {**base, "chamfer_squared_l2": 0.5},
    }
    out = margins_each(summary, rows, OFFICIAL_KEYS)
    assert [m["r2ldm"] for m in out] == ["R2LDM as published", "R2LDM"]
    assert out[0]["metrics"]["CD"]["percent"] == pytest.approx(-15.0)  # the paper's CD margin
    assert out[1]["metrics"]["CD"]["percent"] == pytest.approx(70.0)
    assert out[0]["metrics"]["JSD"]["paper"] == -30.0


def test_quality_command_writes_both_metric_sets(vod_root, tmp_path):
    import json

    from click.testing import CliRunner

    from msdnet.benchmarks.cli import main

    out = tmp_path / "q"
    args = ["quality", "--dataset", "vod", "--data", str(vod_root), "--split", "all", "--grid", "tiny"]
    res = CliRunner().invoke(main, [*args, "--pictures", "0", "--metrics", "both", "--out", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "results.json").read_text())
    radar = doc["official"]["summary"]["4D radar"]
    assert radar["pairs_evaluated"] + radar["pairs_skipped_empty"] == doc["evaluation"]["frames"]
    assert "authors' formulas" in (out / "results.md").read_text()
    bad = CliRunner().invoke(main, [*args, "--metrics", "nope", "--out", str(out)])
    assert bad.exit_code == 2
