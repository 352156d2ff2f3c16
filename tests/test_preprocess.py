"""Preprocessing: grid/FOV crops and ground removal, synthetic and on the real frames."""

from __future__ import annotations

import numpy as np
import pypatchworkpp
import pytest

from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.io.datasets import AstyxDataset, Frame, VodDataset, preprocess
from msdnet.runtime.io.datasets.preprocess import GroundConfig, crop_mask, ground_mask, preprocess_frame
from msdnet.runtime.spec.grid import GRID_PRESETS, GridConfig

PAPER = GRID_PRESETS["paper"]
HEIGHT = 1.8  # synthetic LiDAR height above the road, m


def plane_and_boxes(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """LiDAR-frame cloud: ring-like road at z = -HEIGHT and four car-sized boxes on it.

    Returns (N, 3) [x, y, z] and (N,) bool ground truth (True = road).
    """
    rng = np.random.default_rng(seed)
    radii = np.geomspace(3.0, 40.0, 40)  # scan rings get sparser with range
    az = np.radians(np.arange(-75.0, 75.0, 0.4))
    r, a = np.meshgrid(radii, az)
    road = np.stack([r * np.cos(a), r * np.sin(a), np.full_like(r, -HEIGHT)], -1).reshape(-1, 3)
    road[:, 2] += rng.normal(0.0, 0.02, len(road))
    boxes = []
    for cx, cy in ((8.0, 3.0), (15.0, -4.0), (22.0, 1.0), (12.0, 8.0)):
        pts = rng.uniform([-2.0, -0.9, 0.15], [2.0, 0.9, 1.5], size=(1500, 3))
        side = rng.integers(0, 3, len(pts))  # push each point onto a face: x, y or top
        pts[side == 0, 0] = np.sign(pts[side == 0, 0]) * 2.0
        pts[side == 1, 1] = np.sign(pts[side == 1, 1]) * 0.9
        pts[side == 2, 2] = 1.5
        boxes.append(pts + [cx, cy, -HEIGHT])
    xyz = np.concatenate([road, *boxes])
    truth = np.zeros(len(xyz), bool)
    truth[: len(road)] = True
    return xyz, truth


@pytest.mark.parametrize("method", ["patchwork", "plane"])
def test_ground_removed_from_plane_and_boxes(method):
    xyz, truth = plane_and_boxes()
    res = ground_mask(xyz, GroundConfig(method=method))
    assert res.method == method
    assert res.sensor_height == pytest.approx(HEIGHT, abs=0.05)
    assert res.mask[truth].mean() > 0.95  # road found
    assert res.mask[~truth].mean() < 0.03  # boxes kept


def test_patchwork_failure_falls_back_to_plane(monkeypatch):
    def broken(params):
        raise RuntimeError("no")

    monkeypatch.setattr(pypatchworkpp, "patchworkpp", broken)
    xyz, truth = plane_and_boxes(seed=1)
    res = ground_mask(xyz)
    assert res.method == "plane"
    assert res.mask[truth].mean() > 0.95 and res.mask[~truth].mean() < 0.03


def test_tilted_plane_fit():
    xyz, truth = plane_and_boxes(seed=2)
    tilt = np.radians(4.0)  # the LiDAR pitched down 4 degrees
    rot = np.array([[np.cos(tilt), 0, np.sin(tilt)], [0, 1, 0], [-np.sin(tilt), 0, np.cos(tilt)]])
    res = ground_mask(xyz @ rot.T, GroundConfig(method="plane"))
    assert res.mask[truth].mean() > 0.95 and res.mask[~truth].mean() < 0.03


def test_crop_mask_box_and_fov():
    grid = GridConfig((0.0, -10.0, -2.0, 20.0, 10.0, 4.0), (0.5, 0.5, 0.5), fov_deg=45.0)
    pts = np.array(
        [
            [5.0, 0.0, 0.0],  # inside
            [5.0, 4.9, 0.0],  # inside, 44.4 deg
            [5.0, 5.2, 0.0],  # inside the box, 46 deg: out of the FOV
            [20.0, 0.0, 0.0],  # x on the upper bound: out (half-open)
            [0.0, 0.0, 0.0],  # x on the lower bound: in
            [5.0, 0.0, 4.5],  # too high
        ]
    )
    np.testing.assert_array_equal(crop_mask(pts, grid), [1, 1, 0, 0, 1, 0])
    np.testing.assert_array_equal(crop_mask(pts, grid, fov=False), [1, 1, 1, 0, 1, 0])


def test_preprocess_frame_works_in_the_lidar_frame(monkeypatch):
    xyz, truth = plane_and_boxes(seed=3)
    radar_in_lidar = np.array([2.5, 0.0, -1.2])  # radar 2.5 m ahead of and 1.2 m below the LiDAR
    r2l = np.eye(4)
    r2l[:3, 3] = radar_in_lidar
    lidar_radar = (xyz - radar_in_lidar).astype(np.float32)  # road at z = -0.6 in radar frame
    radar = np.array([[10, 0, 0, 1, 0, 0, 0], [40, 0, 0, 1, 0, 0, 0], [5, 0, -3, 1, 0, 0, 0]])
    frame = Frame(
        "0",
        PointCloud(radar.astype(np.float32), ("x", "y", "z", "rcs", "v_r", "v_r_compensated", "t")),
        PointCloud(lidar_radar, ("x", "y", "z")),
        None,
        r2l,
    )
    seen = []

    def recording(xyz, cfg=None):
        seen.append(np.array(xyz))
        return ground_mask(xyz, cfg)

    monkeypatch.setattr(preprocess, "ground_mask", recording)
    out = preprocess_frame(frame, PAPER)
    road_z = np.median(seen[0][:, 2])
    assert road_z == pytest.approx(-HEIGHT, abs=0.05)  # classified in the LiDAR's own frame
    np.testing.assert_array_equal(out.radar.xyz, [[10, 0, 0]])  # box crop only
    kept = {tuple(p) for p in out.lidar.xyz.round(4)}
    inside = crop_mask(lidar_radar, PAPER)
    truth_kept = [tuple(p) in kept for p in lidar_radar.round(4)]
    assert not np.any(np.array(truth_kept) & ~inside)  # nothing outside box/FOV survives
    assert np.mean(np.array(truth_kept)[truth & inside]) < 0.05  # road removed
    assert np.mean(np.array(truth_kept)[~truth & inside]) > 0.97  # boxes kept
    assert len(preprocess_frame(frame, PAPER, remove_ground=False).lidar) == inside.sum()


def _ground_mode_removed(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """(share of the near-ground band left, share of points > 0.8 m above ground left)."""
    hist, edges = np.histogram(before, bins=np.arange(-2.0, 4.0, 0.1))
    g = edges[np.argmax(hist)] + 0.05
    near = lambda z: np.sum(np.abs(z - g) < 0.25)  # noqa: E731
    high = lambda z: np.sum(z > g + 0.8)  # noqa: E731
    return near(after) / near(before), high(after) / high(before)


def test_real_vod_ground_removed(vod_root):
    for frame in VodDataset(vod_root):
        before = preprocess_frame(frame, PAPER, remove_ground=False)
        after = preprocess_frame(frame, PAPER)
        assert 30_000 < len(before.lidar) < 50_000
        near_left, high_left = _ground_mode_removed(before.lidar.xyz[:, 2], after.lidar.xyz[:, 2])
        assert near_left < 0.2, frame.frame_id
        assert high_left > 0.9, frame.frame_id
        assert len(after.radar) == np.sum(crop_mask(frame.radar.xyz, PAPER, fov=False))


def test_real_astyx_ground_removed(astyx_root):
    ds = AstyxDataset(astyx_root)
    for frame in (ds[0], ds[200]):
        before = preprocess_frame(frame, PAPER, remove_ground=False)
        after = preprocess_frame(frame, PAPER)
        near_left, high_left = _ground_mode_removed(before.lidar.xyz[:, 2], after.lidar.xyz[:, 2])
        assert near_left < 0.25, frame.frame_id
        assert high_left > 0.85, frame.frame_id
