"""GICP odometry and ScanContext place recognition on synthetic scenes with known poses."""

from __future__ import annotations

import numpy as np
import pytest

from msdnet.benchmarks.downstream import odometry, place


def _scene(rng: np.random.Generator) -> np.ndarray:
    """(N, 3) world points: walls, poles and boxes scattered over a 120 m square."""
    pts = []
    for _ in range(60):
        cx, cy = rng.uniform(-60, 60, 2)
        w, d, h = rng.uniform(0.5, 6, 3)
        n = 300
        face = rng.integers(0, 4, n)
        u, v = rng.uniform(-0.5, 0.5, n), rng.uniform(0, 1, n)
        x = np.where(face < 2, cx + u * w, cx + np.where(face == 2, -w / 2, w / 2))
        y = np.where(face < 2, cy + np.where(face == 0, -d / 2, d / 2), cy + u * d)
        pts.append(np.stack([x, y, v * h], axis=1))
    return np.concatenate(pts)


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    t = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    t[:2, :2] = [[c, -s], [s, c]]
    t[:2, 3] = [x, y]
    return t


def _observe(world: np.ndarray, pose: np.ndarray, radius: float = 40.0) -> np.ndarray:
    local = (np.linalg.inv(pose) @ np.c_[world, np.ones(len(world))].T).T[:, :3]
    return local[np.hypot(local[:, 0], local[:, 1]) < radius]


def test_relative_errors_by_hand():
    gt = [_pose(1.0, 0.0, 0.0), _pose(1.0, 0.0, 0.0)]
    est = [_pose(1.1, 0.0, 0.0), _pose(1.0, 0.0, np.radians(2.0))]
    err = odometry.relative_errors(est, gt)
    assert err.translation_m == pytest.approx(0.05)
    assert err.rotation_deg == pytest.approx(1.0)
    assert err.translation_pct == pytest.approx(100 * 0.1 / 2.0)
    assert err.pairs == 2


def test_gicp_recovers_known_motion():
    rng = np.random.default_rng(0)
    world = _scene(rng)
    poses = [_pose(1.2 * k, 0.1 * k, np.radians(1.5 * k)) for k in range(5)]
    clouds = [_observe(world, p) for p in poses]
    est = odometry.gicp_odometry(clouds)
    err = odometry.relative_errors(est, odometry.relative_from_poses(poses))
    assert err.translation_m < 0.05 and err.rotation_deg < 0.2


def test_scan_context_is_rotation_invariant():
    rng = np.random.default_rng(1)
    world = _scene(rng)
    cfg = place.ScanContextConfig()
    a = place.scan_context(_observe(world, _pose(0, 0, 0)), cfg)
    b = place.scan_context(_observe(world, _pose(0, 0, np.radians(90))), cfg)
    c = place.scan_context(_observe(world, _pose(30, 20, 0)), cfg)
    assert place.sc_distance(a, b) < 0.05 < place.sc_distance(a, c)


def test_recall_on_a_loop():
    rng = np.random.default_rng(2)
    world = _scene(rng)
    # a 40-frame square loop of 4 m steps, then the first 10 frames again
    path = [(4.0 * k, 0.0) for k in range(10)] + [(40.0, 4.0 * k) for k in range(10)]
    path += [(40.0 - 4.0 * k, 40.0) for k in range(10)] + [(0.0, 40.0 - 4.0 * k) for k in range(10)]
    path += path[:10]
    poses = [_pose(x, y, 0.0) for x, y in path]
    clouds = [_observe(world, p) for p in poses]
    res = place.recall_at_k(clouds, np.array(path), exclude_recent=20)
    assert res.queries >= 10  # the revisited first leg (and the loop closing corner)
    assert res.recall[1] >= 0.8 and res.recall[5] >= res.recall[1]
