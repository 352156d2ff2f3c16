"""Astyx 3D boxes (scalar-first quaternion, radar frame) and object-level quality
(``benchmarks.quality.objects``): hand-made boxes, then one real frame."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from msdnet.benchmarks.quality import objects as ob
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.datasets import AstyxDataset
from msdnet.runtime.io.datasets.astyx_boxes import Boxes, quat_to_matrix, read_astyx_boxes
from msdnet.runtime.io.datasets.preprocess import preprocess_frame
from msdnet.runtime.metrics.cloud import chamfer_distance
from msdnet.runtime.metrics.crop import crop_to_grid
from msdnet.runtime.spec.grid import GridConfig

GRID = GridConfig((0.0, -16.0, -2.0, 32.0, 16.0, 4.0), (0.2, 0.2, 0.3))  # the lite grid, FOV 60 deg
YAW90 = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]  # w, x, y, z: 90 deg about z


def _box(center, dims, quat, cls="Car") -> Boxes:
    return Boxes(
        np.asarray([center], float),
        np.asarray([dims], float),
        quat_to_matrix(quat)[None],
        (cls,),
        np.zeros(1, int),
    )


def _write_labels(path: Path, objects: list[dict]) -> Path:
    path.write_text(json.dumps({"objects": objects}), encoding="utf-8")
    return path


def test_quaternion_is_scalar_first():
    np.testing.assert_allclose(quat_to_matrix([1.0, 0.0, 0.0, 0.0]), np.eye(3))
    r = quat_to_matrix(YAW90)
    np.testing.assert_allclose(r @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)  # box x -> radar y
    np.testing.assert_allclose(quat_to_matrix([2.0, 0.0, 0.0, 0.0]), np.eye(3))  # normalised


def test_reader_turns_the_box(tmp_path):
    obj = {"classname": "Car", "center3d": [10.0, 2.0, 0.0], "dimension3d": [4.0, 2.0, 1.5]}
    path = _write_labels(tmp_path / "000001.json", [{**obj, "orientation_quat": YAW90, "occlusion": 1}])
    b = read_astyx_boxes(path)
    assert len(b) == 1 and b.classes == ("Car",) and b.occlusion.tolist() == [1]
    # length 4 m runs along radar y: 1.9 m off the centre along y is inside, along x is not
    assert b.contains(np.array([[10.0, 3.9, 0.0]]), 0).all()
    assert not b.contains(np.array([[11.9, 2.0, 0.0]]), 0).any()
    # read scalar last the same numbers are a 180 deg turn about an axis in the x-y plane instead
    last = read_astyx_boxes(
        _write_labels(tmp_path / "l.json", [{**obj, "orientation_quat": YAW90[1:] + YAW90[:1]}])
    )
    assert not np.allclose(last.rotations, b.rotations)
    corners = b.corners_bev(0)
    np.testing.assert_allclose(sorted(corners[:, 0]), [9.0, 9.0, 11.0, 11.0], atol=1e-12)
    np.testing.assert_allclose(sorted(corners[:, 1]), [0.0, 0.0, 4.0, 4.0], atol=1e-12)


def test_reader_refusals_and_empty(tmp_path):
    assert len(read_astyx_boxes(_write_labels(tmp_path / "e.json", []))) == 0
    bad = {
        "classname": "Car",
        "center3d": [1, 2, 3],
        "dimension3d": [1, 1, 1],
        "orientation_quat": [0, 0, 0, 0],
    }
    with pytest.raises(MsdnetError, match="zero quaternion"):
        read_astyx_boxes(_write_labels(tmp_path / "z.json", [bad]))
    with pytest.raises(MsdnetError, match="needs center3d"):
        read_astyx_boxes(_write_labels(tmp_path / "m.json", [{"classname": "Car"}]))


def test_grown_box_edges():
    """A rotated box (30 deg): points a hair inside and outside the box grown by GROW."""
    yaw = math.radians(30)
    b = _box([12.0, 1.0, 0.5], [4.0, 2.0, 1.5], [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    axis_x = np.array([math.cos(yaw), math.sin(yaw), 0.0])  # the box's length axis in the radar frame
    centre = b.centers[0]
    just_in = centre + (2.0 + ob.GROW - 1e-6) * axis_x
    just_out = centre + (2.0 + ob.GROW + 1e-6) * axis_x
    assert b.contains(just_in[None], 0, ob.GROW).all()
    assert not b.contains(just_out[None], 0, ob.GROW).any()
    assert not b.contains(just_in[None], 0).any()  # outside the box itself
    # the same distance along the box's width axis leaves it (width 2 m); along the height too
    axis_y = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    assert not b.contains((centre + 2.0 * axis_y)[None], 0, ob.GROW).any()
    assert b.contains((centre + (1.0 + ob.GROW - 1e-6) * axis_y)[None], 0, ob.GROW).all()
    assert not b.contains((centre + [0.0, 0.0, 0.75 + ob.GROW + 1e-6])[None], 0, ob.GROW).any()


def _cloud_in_box(b: Boxes, n: int, rng: np.random.Generator) -> np.ndarray:
    local = (rng.random((n, 3)) - 0.5) * b.dims[0]
    return local @ b.rotations[0].T + b.centers[0]


def test_scored_objects_and_scores():
    rng = np.random.default_rng(0)
    b = _box([12.0, 1.0, 0.5], [4.0, 2.0, 1.5], YAW90)
    far = _box([40.0, 0.0, 0.0], [4.0, 2.0, 1.5], YAW90)  # centre outside the grid box
    both = Boxes(
        np.vstack([b.centers, far.centers]), np.vstack([b.dims, far.dims]),
        np.vstack([b.rotations, far.rotations]), ("Car", "Truck"), np.zeros(2, int),
    )  # fmt: skip
    seen = _cloud_in_box(b, ob.MIN_LIDAR_POINTS, rng)
    objs = ob.scored_objects(both, seen, GRID)
    assert len(objs) == 1 and objs.boxes.classes == ("Car",) and len(objs.lidar[0]) == ob.MIN_LIDAR_POINTS
    assert len(ob.scored_objects(both, seen[:-1], GRID)) == 0  # 9 points: the LiDAR does not see it
    np.testing.assert_allclose(objs.ranges, [math.hypot(12.0, 1.0)])
    pred = np.vstack([_cloud_in_box(b, ob.HIT_POINTS, rng), [[0.5, 0.0, 0.0]]])  # 5 in, 1 outside
    scores = ob.score_objects(pred, objs)
    assert scores[0, 0] == ob.HIT_POINTS and scores[0, 2] == ob.MIN_LIDAR_POINTS
    assert scores[0, 1] == pytest.approx(chamfer_distance(pred[: ob.HIT_POINTS], objs.lidar[0]))
    miss = ob.score_objects(pred[1:], objs)  # 4 in the box: not hit, no CD
    assert miss[0, 0] == ob.HIT_POINTS - 1 and np.isnan(miss[0, 1])
    tally = ob.ObjectTally()
    tally.add("a", objs, pred, np.zeros((0, 3)))
    tally.add("b", objs, pred[1:], np.zeros((0, 3)))
    s = ob.summarize_objects(tally)
    assert s["overall"]["objects"] == 2 and s["overall"]["hit@5"] == 0.5
    assert s["overall"]["object_cd"] == pytest.approx(scores[0, 1])
    assert s["by_class"]["Car"]["objects"] == 2 and s["by_range"]["10–20 m"]["objects"] == 2
    assert s["by_range"]["0–10 m"]["objects"] == 0 and math.isnan(s["radar_kept"]["share"])
    assert ob.range_band(25.0) == "20–32 m" and ob.range_band(33.0) == "20–32 m"


def test_radar_kept():
    lidar = np.array([[5.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    radar = np.array([[5.1, 0.0, 0.0], [10.0, 0.19, 0.0], [20.0, 0.0, 0.0]])  # two on a surface
    near = ob.near_radar(radar, lidar)
    assert len(near) == 2
    assert ob.radar_kept(near, radar) == 2
    assert ob.radar_kept(near, np.array([[5.0, 0.0, 0.0]])) == 1  # 0.1 m from the first, 5 m from the second
    assert ob.radar_kept(near, np.zeros((0, 3))) == 0


def test_one_real_frame(astyx_root):
    """Frame 000000: the labels, the boxes in the radar frame (they hold the LiDAR), and the scores."""
    ds = AstyxDataset(astyx_root)
    assert ds.has_boxes
    boxes = ds.boxes("000000")
    assert len(boxes) > 3 and boxes.classes[0] == "Car"
    np.testing.assert_allclose(boxes.centers[0], [15.28, 4.24, -0.46])
    frame = preprocess_frame(ds.get("000000"), GRID)
    ref = crop_to_grid(frame.lidar.xyz, GRID)
    objs = ob.scored_objects(boxes, ref, GRID)
    assert 3 <= len(objs) < len(boxes)
    radar = crop_to_grid(frame.radar.xyz, GRID)
    tally = ob.ObjectTally()
    near = ob.near_radar(radar, ref)
    tally.add("000000", objs, radar, near)
    s = ob.summarize_objects(tally)
    assert s["radar_kept"]["share"] == 1.0 and s["radar_kept"]["near"] == len(near) > 10
    assert 0.0 < s["overall"]["hit@5"] <= 1.0 and 0.0 < s["overall"]["object_cd"] < 1.0
    # the LiDAR itself hits every object it sees, and its own object CD is 0
    lidar_tally = ob.ObjectTally()
    lidar_tally.add("000000", objs, ref, near)
    lo = ob.summarize_objects(lidar_tally)["overall"]
    assert lo["hit@5"] == 1.0 and lo["object_cd"] == 0.0 and lo["points"] == lo["lidar_points"]
    # a frame without a label file has no box
    assert len(AstyxDataset(astyx_root).boxes("999999")) == 0


def test_quality_suite_scores_objects(astyx_root, tmp_path):
    """``msdnet-bench quality`` on Astyx: results.json and results.md carry the object section."""
    from msdnet.benchmarks.eval_methods import RawRadar
    from msdnet.benchmarks.quality.suite import run_quality

    ds = AstyxDataset(astyx_root)
    ds.frame_ids = ["000000", "000001"]
    evaluation = {"dataset": "astyx", "data": str(astyx_root), "split": "all"}
    doc = run_quality(ds, evaluation, [RawRadar()], GRID, tmp_path, pictures=1, progress=False)
    s = doc["objects"]["summary"]["4D radar"]
    assert s["overall"]["objects"] == len(doc["objects"]["per_object"]["4D radar"]) >= 6
    assert s["radar_kept"]["share"] == 1.0 and "Car" in s["by_class"]
    assert doc["objects"]["definition"]["min_lidar_points"] == ob.MIN_LIDAR_POINTS
    text = (tmp_path / "results.md").read_text(encoding="utf-8")
    assert "## Objects" in text and "Per range band" in text
    assert (tmp_path / "pictures" / "000000.png").is_file()
