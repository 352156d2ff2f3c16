"""Point-cloud container and file I/O: real files, round trips, and every kind of bad input."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msdnet.runtime.engine.pointcloud import PointCloud, canonical_column, concat_clouds
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io import atomic
from msdnet.runtime.io import files as io
from msdnet.runtime.io.files import LIDAR_COLUMNS, VOD_RADAR_COLUMNS, read_cloud, write_cloud


def _rows(n: int, c: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, c)).astype(np.float32)


# ---------------------------------------------------------------- PointCloud


def test_pointcloud_helpers():
    pts = _rows(5, 5)
    cloud = PointCloud(pts, ("x", "y", "z", "rcs", "v_r"))
    assert len(cloud) == 5
    np.testing.assert_array_equal(cloud.xyz, pts[:, :3])
    np.testing.assert_array_equal(cloud.column("rcs"), pts[:, 3])
    sub = cloud.select(["v_r", "x", "y", "z"])
    assert sub.columns == ("v_r", "x", "y", "z")
    np.testing.assert_array_equal(sub.xyz, pts[:, :3])  # xyz found by name, not position
    with pytest.raises(MsdnetError, match="'time'"):
        cloud.select(["x", "time"])
    with pytest.raises(MsdnetError, match="'mag'"):
        cloud.column("mag")
    with pytest.raises(MsdnetError, match="no z"):
        PointCloud(pts[:, :2], ("x", "y"))


def test_transformed_moves_xyz_only():
    cloud = PointCloud(np.array([[1, 0, 0, 7.0]], np.float32), ("x", "y", "z", "rcs"))
    t = np.eye(4)
    t[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90 deg about z
    t[:3, 3] = [10, 20, 30]
    out = cloud.transformed(t)
    np.testing.assert_allclose(out.points, [[10, 21, 30, 7]], atol=1e-6)
    np.testing.assert_array_equal(cloud.points, [[1, 0, 0, 7]])  # input untouched
    both = concat_clouds([cloud, out])
    assert len(both) == 2 and both.columns == cloud.columns


def test_canonical_column_names():
    assert canonical_column("LaserID") == "laser_id"
    assert canonical_column("V_r") == "v_r"
    assert canonical_column("Reflectivity") == "reflectivity"
    assert canonical_column("RCS") == "rcs"


# ---------------------------------------------------------------- real files


def test_real_vod_bins(vod_root):
    radar = read_cloud(vod_root / "radar/training/velodyne/00549.bin")
    assert radar.columns == VOD_RADAR_COLUMNS and len(radar) == 322
    assert radar.dropped_nonfinite == 0
    lidar = read_cloud(vod_root / "lidar/training/velodyne/00549.bin")
    assert lidar.columns == LIDAR_COLUMNS and len(lidar) == 2684352 // 16
    assert lidar.source.endswith("00549.bin")


def test_real_astyx_txt(astyx_root):
    radar = read_cloud(astyx_root / "radar_6455/000000.txt")
    assert radar.columns == ("x", "y", "z", "v_r", "mag") and len(radar) == 831
    np.testing.assert_allclose(radar.points[0], [0.1081, 2.3057, -0.2791, 0.0, 48.0], atol=1e-6)
    lidar = read_cloud(astyx_root / "lidar_vlp16/000000.txt")
    assert lidar.columns == ("x", "y", "z", "reflectivity", "laser_id", "timestamp")
    assert len(lidar) == 8312
    np.testing.assert_allclose(lidar.points[0, :5], [9.19, 28.02, 2.58, 5, 5], atol=1e-5)


# ---------------------------------------------------------------- .bin layouts


def test_bin_kind_by_size_path_and_explicit(tmp_path):
    radar_rows, lidar_rows = _rows(3, 7), _rows(3, 4)
    (tmp_path / "r.bin").write_bytes(radar_rows.tobytes())  # 84 bytes: only 28 divides
    (tmp_path / "l.bin").write_bytes(lidar_rows.tobytes())  # 48 bytes: only 16 divides
    assert read_cloud(tmp_path / "r.bin").columns == VOD_RADAR_COLUMNS
    assert read_cloud(tmp_path / "l.bin").columns == LIDAR_COLUMNS
    both = _rows(7, 4)  # 112 bytes: 4 radar rows or 7 LiDAR rows
    (tmp_path / "both.bin").write_bytes(both.tobytes())
    with pytest.raises(MsdnetError, match="pass kind="):
        read_cloud(tmp_path / "both.bin")
    assert len(read_cloud(tmp_path / "both.bin", kind="lidar")) == 7
    assert len(read_cloud(tmp_path / "both.bin", kind="vod_radar")) == 4
    for folder, cols in (("radar_5frames/training/velodyne", 7), ("lidar/training/velodyne", 4)):
        d = tmp_path / folder
        d.mkdir(parents=True)
        (d / "0.bin").write_bytes(both.tobytes())
        assert len(read_cloud(d / "0.bin").columns) == cols


def test_bin_bad_size_empty_unknown(tmp_path):
    (tmp_path / "odd.bin").write_bytes(b"\0" * 30)
    with pytest.raises(MsdnetError, match="whole number"):
        read_cloud(tmp_path / "odd.bin", kind="vod_radar")
    (tmp_path / "empty.bin").write_bytes(b"")  # what a scan with no output point writes
    assert len(read_cloud(tmp_path / "empty.bin", kind="lidar")) == 0
    with pytest.raises(MsdnetError, match="empty .bin .no rows. of unknown layout"):
        read_cloud(tmp_path / "empty.bin")
    (tmp_path / "empty.npy").write_bytes(b"")
    with pytest.raises(MsdnetError, match="empty file"):
        read_cloud(tmp_path / "empty.npy")
    (tmp_path / "a.xyz").write_text("1 2 3\n")
    with pytest.raises(MsdnetError, match="unknown point-cloud extension"):
        read_cloud(tmp_path / "a.xyz")
    with pytest.raises(MsdnetError, match="cannot read"):
        read_cloud(tmp_path / "missing.bin")
    with pytest.raises(MsdnetError, match="unknown kind"):
        read_cloud(tmp_path / "odd.bin", kind="radar")


def test_point_cap_checked_before_allocating(tmp_path, monkeypatch):
    path = tmp_path / "big.bin"
    path.write_bytes(_rows(10, 4).tobytes())

    def boom(*args, **kwargs):
        raise AssertionError("allocated before checking the cap")

    monkeypatch.setattr(np, "fromfile", boom)
    with pytest.raises(MsdnetError, match="exceeds the cap of 5"):
        read_cloud(path, kind="lidar", max_points=5)
    np.save(tmp_path / "big.npy", _rows(10, 3))
    monkeypatch.setattr(np, "load", boom)
    with pytest.raises(MsdnetError, match="exceeds the cap"):
        read_cloud(tmp_path / "big.npy", max_points=5)


def test_nonfinite_rows_dropped_and_counted(tmp_path):
    rows = _rows(6, 4)
    rows[1, 2] = np.nan
    rows[4, 3] = np.inf
    (tmp_path / "l.bin").write_bytes(rows.tobytes())
    cloud = read_cloud(tmp_path / "l.bin", kind="lidar")
    assert len(cloud) == 4 and cloud.dropped_nonfinite == 2
    np.testing.assert_array_equal(cloud.points, rows[[0, 2, 3, 5]])
    (tmp_path / "t.txt").write_text("X Y Z Mag\n1 2 3 4\nnan 2 3 4\n5 6 7 8\n")
    cloud = read_cloud(tmp_path / "t.txt")
    assert len(cloud) == 2 and cloud.dropped_nonfinite == 1 and cloud.columns[-1] == "mag"


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize("fmt", ["bin", "npy", "pcd", "ply"])
def test_round_trip_keeps_values_and_names(tmp_path, fmt):
    cols = ("x", "y", "z", "rcs", "v_r_compensated")
    cloud = PointCloud(_rows(50, 5, seed=3), cols)
    path = write_cloud(tmp_path / f"c.{fmt}", cloud)
    assert path.exists() and os.listdir(tmp_path) == [f"c.{fmt}"]  # no temp files left
    back = read_cloud(path, columns=cols if fmt in ("bin", "npy") else None)
    assert back.columns == cols
    np.testing.assert_array_equal(back.points, cloud.points)


@settings(max_examples=25, deadline=None)
@given(n=st.integers(0, 40), c=st.integers(3, 9), seed=st.integers(0, 1000))
def test_bin_round_trip_any_width(tmp_path_factory, n, c, seed):
    d = tmp_path_factory.mktemp("rt")
    cols = ("x", "y", "z", *(f"f{i}" for i in range(3, c)))
    cloud = PointCloud(_rows(n, c, seed), cols)
    path = write_cloud(d / "c.bin", cloud)
    back = read_cloud(path, columns=cols)
    np.testing.assert_array_equal(back.points, cloud.points)


def test_write_is_atomic_and_replaces(tmp_path, monkeypatch):
    target = tmp_path / "c.npy"
    first = PointCloud(_rows(4, 3), ("x", "y", "z"))
    write_cloud(target, first)
    assert target.stat().st_mode & 0o777 == 0o666 & ~atomic._umask()  # not mkstemp's 0600

    def failing_save(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "save", failing_save)
    with pytest.raises(MsdnetError, match="c.npy: cannot write: disk full"):
        write_cloud(target, PointCloud(_rows(9, 3), ("x", "y", "z")))
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["c.npy"]  # the old file intact, no temp left
    np.testing.assert_array_equal(read_cloud(target).points, first.points)
    with pytest.raises(MsdnetError, match="cannot write format"):
        write_cloud(tmp_path / "c.las", first)


# ---------------------------------------------------------------- broken content


@pytest.mark.parametrize("suffix", [".npy", ".pcd", ".ply", ".txt"])
def test_garbage_is_one_msdnet_error(tmp_path, suffix):
    path = tmp_path / f"junk{suffix}"
    path.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(MsdnetError) as err:
        read_cloud(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_npy_bad_arrays(tmp_path):
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(MsdnetError):
        read_cloud(tmp_path / "obj.npy")
    np.save(tmp_path / "two.npy", _rows(5, 2))
    with pytest.raises(MsdnetError, match=r"\(N, >=3\)"):
        read_cloud(tmp_path / "two.npy")
    np.save(tmp_path / "six.npy", _rows(5, 6))
    assert read_cloud(tmp_path / "six.npy").columns == ("x", "y", "z", "f3", "f4", "f5")
    rec = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("RCS", "<f8")])
    np.save(tmp_path / "rec.npy", rec)
    assert read_cloud(tmp_path / "rec.npy").columns == ("x", "y", "z", "rcs")


def test_txt_bad_rows(tmp_path):
    (tmp_path / "a.txt").write_text("X Y Z\n1 2 3\n1 two 3\n")
    with pytest.raises(MsdnetError, match="unreadable rows"):
        read_cloud(tmp_path / "a.txt")
    (tmp_path / "b.txt").write_text("X Y Z Mag\n1 2 3\n")
    with pytest.raises(MsdnetError, match="header names 4"):
        read_cloud(tmp_path / "b.txt")
    (tmp_path / "c.txt").write_text("\n\n   \n")
    with pytest.raises(MsdnetError, match="no rows"):
        read_cloud(tmp_path / "c.txt")
    (tmp_path / "d.txt").write_text("\nX Y Z V_r Mag\n")  # a radar frame with no detections
    assert len(read_cloud(tmp_path / "d.txt")) == 0


def test_module_constants():
    assert io.MAX_POINTS == 5_000_000
