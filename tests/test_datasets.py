"""Dataset readers on the real VoD / Astyx samples and on small synthetic layouts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.datasets import AstyxDataset, VodDataset, open_dataset, split_contiguous

# camera axes from a sensor's x forward / y left / z up: x_cam = -y, y_cam = -z, z_cam = x
R_CAM = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def _rigid(r: np.ndarray, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def _calib_text(t_cam_sensor: np.ndarray) -> str:
    p2 = "P2: 1000 0 960 0 0 1000 600 0 0 0 1 0"
    tr = " ".join(f"{v:.12f}" for v in t_cam_sensor[:3].ravel())
    return f"{p2}\nR0_rect: 1 0 0 0 1 0 0 0 1\nTr_velo_to_cam: {tr}\nTr_imu_to_velo:\n"


def _pose(k: int, x: float) -> np.ndarray:
    """Radar pose of synthetic frame k: at odom (x, 0, 0.5), yawed 0.1 rad per frame."""
    c, s = np.cos(0.1 * k), np.sin(0.1 * k)
    return _rigid(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [x, 0.0, 0.5])


def make_vod(root: Path, xs=(0.0, 1.0, 2.0), world_point=(10.0, 2.0, 0.5)) -> dict:
    """A VoD-layout folder: ego radar at odom (x_k, 0, 0.5), one static radar target."""
    t_cam_lidar = _rigid(R_CAM, [0.1, -0.4, -0.9])
    t_cam_radar = _rigid(R_CAM, [0.05, 1.0, 1.4])
    for d in ("lidar/training/velodyne", "lidar/training/calib", "lidar/training/pose"):
        (root / d).mkdir(parents=True, exist_ok=True)
    for d in ("radar/training/velodyne", "radar/training/calib"):
        (root / d).mkdir(parents=True, exist_ok=True)
    w = np.append(np.asarray(world_point), 1.0)
    for k, x in enumerate(xs):
        fid = f"{k:05d}"
        t_odom_radar = _pose(k, x)
        t_odom_cam = t_odom_radar @ np.linalg.inv(t_cam_radar)
        target = (np.linalg.inv(t_odom_radar) @ w)[:3]
        radar = np.array([[*target, -10.0, 0.0, 0.0, 0.0]], np.float32)
        (root / f"radar/training/velodyne/{fid}.bin").write_bytes(radar.tobytes())
        lidar = np.array([[5, 0, -1.5, 9], [6, 1, -1.5, 9]], np.float32)
        (root / f"lidar/training/velodyne/{fid}.bin").write_bytes(lidar.tobytes())
        (root / f"lidar/training/calib/{fid}.txt").write_text(_calib_text(t_cam_lidar))
        (root / f"radar/training/calib/{fid}.txt").write_text(_calib_text(t_cam_radar))
        docs = [{"odomToCamera": t_odom_cam.ravel().tolist()}, {"mapToCamera": [0] * 16}]
        (root / f"lidar/training/pose/{fid}.json").write_text("\n".join(map(json.dumps, docs)))
    return {"t_cam_lidar": t_cam_lidar, "t_cam_radar": t_cam_radar}


# ---------------------------------------------------------------- real VoD


def test_vod_real_frame_549(vod_root):
    ds = VodDataset(vod_root)
    assert ds.frame_ids == ["00549", "01047", "01201"] and len(ds) == 3
    frame = ds.get("00549")
    assert frame.frame_id == "00549"
    assert len(frame.radar) == 322 and frame.radar.columns[3] == "rcs"
    np.testing.assert_allclose(frame.radar_to_lidar[:3, 3], [2.514, 0.061, -1.153], atol=1e-3)
    raw = np.fromfile(vod_root / "lidar/training/velodyne/00549.bin", np.float32).reshape(-1, 4)
    l2r = np.linalg.inv(frame.radar_to_lidar)
    np.testing.assert_allclose(frame.lidar.xyz, raw[:, :3] @ l2r[:3, :3].T + l2r[:3, 3], atol=1e-4)
    # LiDAR ground (densest height band in front) sits ~0.5 m below the radar
    front = frame.lidar.xyz[(frame.lidar.xyz[:, 0] > 3) & (frame.lidar.xyz[:, 0] < 20)]
    hist, edges = np.histogram(front[:, 2], bins=np.arange(-3, 3, 0.1))
    assert -0.8 < edges[np.argmax(hist)] < -0.2
    # radar pose: upright, ~0.5 m above the odom origin's ground level
    pose = frame.pose
    assert pose.shape == (4, 4) and pose[2, 2] > 0.99 and 0.3 < pose[2, 3] < 0.7


def test_vod_accumulation_needs_poses_or_folder(vod_root):
    ds = VodDataset(vod_root, radar_frames=3)
    assert "accumulated here" in ds.radar_source
    # the example frames are far apart: no neighbours exist, the current scan stays alone
    assert len(ds.get("00549").radar) == 322


# ---------------------------------------------------------------- synthetic VoD


def test_vod_synthetic_transforms_and_accumulation(tmp_path):
    t = make_vod(tmp_path)
    ds = VodDataset(tmp_path, radar_frames=3)
    frame = ds[2]
    want = np.linalg.inv(t["t_cam_lidar"]) @ t["t_cam_radar"]
    np.testing.assert_allclose(frame.radar_to_lidar, want, atol=1e-9)
    np.testing.assert_allclose(frame.pose, _pose(2, 2.0), atol=1e-9)
    # the static target lands on one spot from all three scans, time = 0, -1, -2
    spot = (np.linalg.inv(_pose(2, 2.0)) @ [10.0, 2.0, 0.5, 1.0])[:3]
    assert abs(spot[1] - 2.0) > 0.5  # the yaw matters
    np.testing.assert_allclose(frame.radar.xyz, [spot] * 3, atol=1e-5)
    np.testing.assert_array_equal(frame.radar.column("time"), [0, -1, -2])
    assert len(ds[0].radar) == 1  # first frame of the sequence: no previous scans
    single = VodDataset(tmp_path)[2]
    np.testing.assert_allclose(single.radar.xyz, [spot], atol=1e-5)


def test_vod_sequence_boundary_not_accumulated(tmp_path):
    make_vod(tmp_path, xs=(0.0, 100.0, 101.0))
    frame = VodDataset(tmp_path, radar_frames=3)[2]
    assert len(frame.radar) == 2  # frame 1 kept, frame 0 lies 100 m away: another drive


def test_vod_prefers_accumulated_folder(tmp_path):
    make_vod(tmp_path)
    d = tmp_path / "radar_3_scans/training/velodyne"
    d.mkdir(parents=True)
    (d / "00002.bin").write_bytes(np.zeros((5, 7), np.float32).tobytes())
    ds = VodDataset(tmp_path, radar_frames=3)
    assert "radar_3_scans" in ds.radar_source and len(ds[2].radar) == 5


def test_vod_split_file_and_fallback(tmp_path):
    make_vod(tmp_path, xs=tuple(float(i) for i in range(10)))
    assert len(VodDataset(tmp_path, split="val")) == 2  # split_contiguous: the last 20 %
    sets = tmp_path / "lidar/ImageSets"
    sets.mkdir()
    (sets / "val.txt").write_text("00003\n00004\n")
    assert VodDataset(tmp_path, split="val").frame_ids == ["00003", "00004"]
    with pytest.raises(MsdnetError, match="ImageSets/test.txt"):
        VodDataset(tmp_path, split="test")


def test_vod_bad_files_named(tmp_path):
    make_vod(tmp_path)
    calib = tmp_path / "radar/training/calib/00001.txt"
    calib.unlink()
    with pytest.raises(MsdnetError) as err:
        VodDataset(tmp_path)[1]
    assert str(calib) in str(err.value)
    pose = tmp_path / "lidar/training/pose/00002.json"
    pose.write_text('{"odomToCamera": [1, 0, ')
    with pytest.raises(MsdnetError, match="broken JSON") as err:
        VodDataset(tmp_path)[2]
    assert str(pose) in str(err.value)
    (tmp_path / "lidar/training/calib/00000.txt").write_text("P2: 1 2 3\n")
    with pytest.raises(MsdnetError, match="no Tr_velo_to_cam"):
        VodDataset(tmp_path)[0]
    with pytest.raises(MsdnetError, match="folder not found"):
        VodDataset(tmp_path / "nowhere")


def test_vod_accumulation_without_poses_refused(tmp_path):
    make_vod(tmp_path)
    for p in (tmp_path / "lidar/training/pose").iterdir():
        p.unlink()
    (tmp_path / "lidar/training/pose").rmdir()
    assert VodDataset(tmp_path)[1].pose is None
    with pytest.raises(MsdnetError, match="needs radar_3frames"):
        VodDataset(tmp_path, radar_frames=3)[1]


# ---------------------------------------------------------------- Astyx


def test_astyx_real_frame_0(astyx_root):
    ds = AstyxDataset(astyx_root)
    assert len(ds) == 440 and ds.frame_ids[0] == "000000" and ds.frame_ids[-1] == "000439"
    frame = ds[0]
    assert len(frame.radar) == 831 and len(frame.lidar) == 8312 and frame.pose is None
    calib = json.loads((astyx_root / "calibration/000000.json").read_text())
    t_lidar = next(
        np.array(s["calib_data"]["T_to_ref_COS"])
        for s in calib["sensors"]
        if s["sensor_uid"] == "lidar_vlp16"
    )
    raw = np.loadtxt(astyx_root / "lidar_vlp16/000000.txt", skiprows=1)[:, :3]
    np.testing.assert_allclose(frame.lidar.xyz, raw @ t_lidar[:3, :3].T + t_lidar[:3, 3], atol=1e-4)
    np.testing.assert_allclose(frame.radar_to_lidar, np.linalg.inv(t_lidar), atol=1e-9)
    xyz = frame.lidar.xyz
    assert (xyz[:, 0] > 0).mean() > 0.99  # in front of the radar
    hist, edges = np.histogram(xyz[(xyz[:, 0] > 3) & (xyz[:, 0] < 15), 2], np.arange(-3, 3, 0.1))
    assert -2.0 < edges[np.argmax(hist)] < -1.0  # road ~1.5 m below the radar


def test_astyx_contiguous_split(astyx_root):
    train = AstyxDataset(astyx_root, split="train").frame_ids
    val = AstyxDataset(astyx_root, split="val").frame_ids
    assert len(train) == 352 and len(val) == 88 and not set(train) & set(val)
    assert val == [f"{i:06d}" for i in range(352, 440)]


def test_astyx_bad_calibration_named(tmp_path):
    for d in ("radar_6455", "lidar_vlp16", "calibration"):
        (tmp_path / d).mkdir()
    (tmp_path / "radar_6455/000000.txt").write_text("\nX Y Z V_r Mag\n1 2 3 0 40\n")
    (tmp_path / "lidar_vlp16/000000.txt").write_text("X Y Z Reflectivity LaserID Timestamp\n")
    calib = tmp_path / "calibration/000000.json"
    calib.write_text("{not json")
    ds = AstyxDataset(tmp_path)  # no dataset.json: frames listed from radar_6455/
    with pytest.raises(MsdnetError, match="broken JSON") as err:
        ds[0]
    assert str(calib) in str(err.value)
    calib.write_text(json.dumps({"sensors": []}))
    with pytest.raises(MsdnetError, match="no T_to_ref_COS for radar_6455"):
        ds[0]
    (tmp_path / "dataset.json").write_text("[1, 2")
    with pytest.raises(MsdnetError, match="dataset.json: broken JSON"):
        AstyxDataset(tmp_path)


# ---------------------------------------------------------------- helpers


def test_split_contiguous_ranges():
    ids = [f"{i:06d}" for i in range(100)]
    train, val = split_contiguous(ids, 0.2)
    assert val == ids[80:] and train == ids[:80]
    train, val = split_contiguous(list(reversed(ids)), 0.2, blocks=4, gap=2)
    assert len(val) == 20 and len(train) == 100 - 20 - 8
    for b in range(4):  # each block of 25: 18 train, 2 dropped, 5 val, in that order
        assert val[5 * b : 5 * b + 5] == ids[25 * b + 20 : 25 * b + 25]
        assert train[18 * b : 18 * b + 18] == ids[25 * b : 25 * b + 18]
    assert split_contiguous(ids, 0.2) == split_contiguous(ids, 0.2)  # never random


def test_open_dataset_names(tmp_path):
    make_vod(tmp_path)
    assert isinstance(open_dataset("sim", tmp_path), VodDataset)
    with pytest.raises(MsdnetError, match="unknown dataset"):
        open_dataset("kitti", tmp_path)
    with pytest.raises(MsdnetError, match="no frame '12345'"):
        open_dataset("vod", tmp_path).get("12345")
