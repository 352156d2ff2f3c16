"""msdnet-data pair: a bag of the three VoD example frames -> a VoD folder that scores as the example."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

pytest.importorskip("rosbags")

from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402
from msdnet.runtime.frontends.data.cli import main  # noqa: E402
from msdnet.runtime.frontends.densify import DensifyOptions  # noqa: E402
from msdnet.runtime.frontends.infer.dataset import run_dataset  # noqa: E402
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL  # noqa: E402
from msdnet.runtime.io.datasets import VodDataset  # noqa: E402
from msdnet.runtime.io.datasets.vod import read_kitti_calib  # noqa: E402
from msdnet.runtime.io.files import read_cloud  # noqa: E402
from msdnet.runtime.io.pairing.transforms import TimedEdge, parse_extrinsic  # noqa: E402
from msdnet.runtime.io.rosbag import POINTCLOUD2, make_pointcloud2  # noqa: E402

IDS = ("00549", "01047", "01201")
T0 = 1_700_000_000 * 10**9
OPTIONS = DensifyOptions()  # msdnet-infer --dataset vod with its defaults


def _transform(types, parent: str, child: str, ns: int, t: np.ndarray):
    q = Rotation.from_matrix(t[:3, :3]).as_quat()  # x y z w
    header = types["std_msgs/msg/Header"](types["builtin_interfaces/msg/Time"](*divmod(ns, 10**9)), parent)
    tr = types["geometry_msgs/msg/Transform"](
        types["geometry_msgs/msg/Vector3"](*t[:3, 3]), types["geometry_msgs/msg/Quaternion"](*q)
    )
    return types["geometry_msgs/msg/TransformStamped"](header, child, tr)


def write_vod_bag(vod_root: Path, path: Path, with_tf_static: bool = True) -> Path:
    """Radar /radar/points and LiDAR /lidar/points (10 ms later) per example frame, 1 s apart,
    /tf_static lidar -> radar (the example's extrinsic), /tf odom -> lidar (its poses), and one
    radar scan with no LiDAR sweep near it."""
    from rosbags import rosbag2, typesys

    store = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    types = store.types
    ds = VodDataset(vod_root)
    with rosbag2.Writer(path, version=9, storage_plugin=rosbag2.StoragePlugin.MCAP) as bag:
        radar = bag.add_connection("/radar/points", POINTCLOUD2, typestore=store)
        lidar = bag.add_connection("/lidar/points", POINTCLOUD2, typestore=store)
        tf = bag.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=store)
        if with_tf_static:
            static = bag.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store)
            msg = types["tf2_msgs/msg/TFMessage"](
                [_transform(types, "lidar", "radar", T0, ds.radar_to_lidar(IDS[0]))]
            )
            bag.write(static, T0, store.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))
        for k, fid in enumerate([*IDS, IDS[0]]):
            ns = T0 + k * 10**9
            scan = read_cloud(vod_root / "radar" / "training" / "velodyne" / f"{fid}.bin")
            msg = make_pointcloud2(store, scan.points, scan.columns, divmod(ns, 10**9), "radar")
            bag.write(radar, ns, store.serialize_cdr(msg, POINTCLOUD2))
            if k == len(IDS):
                continue  # the extra radar scan: no LiDAR sweep within 50 ms
            sweep = read_cloud(vod_root / "lidar" / "training" / "velodyne" / f"{fid}.bin")
            lns = ns + 10_000_000
            msg = make_pointcloud2(store, sweep.points, sweep.columns, divmod(lns, 10**9), "lidar")
            bag.write(lidar, lns, store.serialize_cdr(msg, POINTCLOUD2))
            t_cam_lidar = read_kitti_calib(vod_root / "lidar" / "training" / "calib" / f"{fid}.txt")
            pose = ds.camera_pose(fid) @ t_cam_lidar  # T_odom<-lidar
            msg = types["tf2_msgs/msg/TFMessage"]([_transform(types, "odom", "lidar", lns, pose)])
            bag.write(tf, lns, store.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))
    return path


def _pair(*args: object):
    return CliRunner().invoke(main, ["pair", *map(str, args)])


@pytest.fixture(scope="module")
def scored_example(vod_root, tmp_path_factory):
    pipe = Pipeline.from_dir(BUNDLED_MODEL, threads=1)
    rows, failed = run_dataset(pipe, "vod", vod_root, tmp_path_factory.mktemp("ex"), None, None, OPTIONS)
    assert not failed
    return pipe, {r.frame: r for r in rows}


def test_pair_scores_as_the_example(vod_root, tmp_path, scored_example) -> None:
    bag = write_vod_bag(vod_root, tmp_path / "drive")
    out = tmp_path / "paired"
    r = _pair(bag, "--radar-topic", "/radar/points", "--lidar-topic", "/lidar/points", "--out", out)
    assert r.exit_code == 0, r.output
    assert "wrote 3 frame pairs" in r.output and "(3 with poses); dropped 1" in r.output
    assert "radar message 3" in r.output and "no LiDAR sweep within 50 ms" in r.output
    paired = VodDataset(out)
    assert paired.frame_ids == ["00000", "00001", "00002"]
    assert (out / "lidar" / "ImageSets" / "val.txt").read_text().split() == ["00002"]
    pipe, example = scored_example
    rows, failed = run_dataset(pipe, "vod", out, tmp_path / "dense", None, None, OPTIONS)
    assert not failed and len(rows) == 3
    ref = VodDataset(vod_root)
    for row, fid in zip(rows, IDS, strict=True):
        ex = example[fid]
        assert (row.radar_points, row.lidar_points) == (ex.radar_points, ex.lidar_points)
        assert abs(row.dense_cd - ex.dense_cd) < 1e-4 and abs(row.radar_cd - ex.radar_cd) < 1e-4, (row, ex)
        assert abs(row.dense_fscore - ex.dense_fscore) < 1e-3
        assert np.allclose(paired.pose(row.frame), ref.pose(fid), atol=1e-6)  # radar pose in odom
        diff = abs(row.dense_cd - ex.dense_cd), abs(row.radar_cd - ex.radar_cd)
        print(f"{fid}: dense CD {row.dense_cd:.6f} m (|diff| {diff[0]:.1e}), radar |diff| {diff[1]:.1e}")


def test_pair_extrinsic_flag_and_errors(vod_root, tmp_path) -> None:
    bag = write_vod_bag(vod_root, tmp_path / "drive", with_tf_static=False)
    args = ["--radar-topic", "/radar/points", "--lidar-topic", "/lidar/points"]
    r = _pair(bag, *args, "--out", tmp_path / "a")
    assert r.exit_code == 2 and "no /tf_static chain from 'radar' to 'lidar'" in r.output
    t = VodDataset(vod_root).radar_to_lidar(IDS[0])
    rpy = Rotation.from_matrix(t[:3, :3]).as_euler("xyz")
    ext = ",".join(f"{v:.12f}" for v in [*t[:3, 3], *rpy])
    r = _pair(bag, *args, "--out", tmp_path / "b", "--extrinsic", ext, "--max-skew", "0.005")
    assert r.exit_code == 2 and "no frame pairs" in r.output  # 10 ms apart: nothing within 5 ms
    assert not (tmp_path / "b").exists()
    r = _pair(bag, *args, "--out", tmp_path / "c", "--extrinsic", ext)
    assert r.exit_code == 0 and "wrote 3 frame pairs" in r.output, r.output
    assert np.allclose(VodDataset(tmp_path / "c").radar_to_lidar("00000"), t, atol=1e-6)
    r = _pair(bag, "--radar-topic", "/radar", "--lidar-topic", "/lidar/points", "--out", tmp_path / "d")
    assert r.exit_code == 2 and "no topic '/radar'" in r.output
    assert _pair(bag, *args, "--out", tmp_path / "e", "--extrinsic", "1,2").exit_code == 2


def test_timed_edge_interpolates() -> None:
    edge = TimedEdge()
    edge.add(0, parse_extrinsic("0,0,0,0,0,0"))
    edge.add(100, parse_extrinsic("2,0,0,0,0,1"))
    mid = edge.at(50, 10)
    assert np.allclose(mid[:3, 3], [1, 0, 0]) and np.isclose(
        Rotation.from_matrix(mid[:3, :3]).as_euler("xyz")[2], 0.5
    )
    assert edge.at(200, 10) is None and np.allclose(edge.at(105, 10)[:3, 3], [2, 0, 0])
