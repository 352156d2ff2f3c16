"""Writes simulated frames in the View-of-Delft devkit layout, every file atomically.

    DIR/lidar/training/velodyne/<id>.bin   float32 rows x y z intensity (LiDAR frame)
    DIR/lidar/training/calib/<id>.txt      KITTI style; Tr_velo_to_cam = T_cam<-lidar (3x4)
    DIR/lidar/training/pose/<id>.json      odomToCamera, mapToCamera, UTMToCamera, one per line
    DIR/radar/training/velodyne/<id>.bin   float32 rows x y z rcs v_r v_r_compensated time
                                           (--rig astyx: mag in the rcs column, Astyx v_r; rigs.py)
    DIR/radar/training/calib/<id>.txt      Tr_velo_to_cam = T_cam<-radar
    DIR/radar/training/pose/<id>.json      same poses as the LiDAR's
    DIR/{lidar,radar}/ImageSets/{train,val,full}.txt   frame ids, one per line
    DIR/sequences.json                     per sequence: frame ids, loops, moving objects

Frame ids have 5 digits; sequence k owns ids ``k * stride ..`` (``stride`` a multiple of 1000).
The pose values follow VoD: ``<x>ToCamera`` is the camera pose in frame x, ``T_x<-camera``, as a
row-major 4x4 list.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.atomic import atomic_output
from msdnet.runtime.sim import rig

MAX_FRAME_ID = 99_999  # ids are 5 digits
MANAGED = ("lidar", "radar", "sequences.json")  # what the simulator owns inside DIR
SENSORS = ("lidar", "radar")


def id_stride(n_frames: int) -> int:
    """Id distance between consecutive sequences: n_frames rounded up to a multiple of 1000."""
    return max(1000, -(-n_frames // 1000) * 1000)


def frame_id(sequence: int, frame: int, stride: int) -> str:
    """5-digit id of frame ``frame`` of sequence ``sequence``."""
    return f"{sequence * stride + frame:05d}"


def check_capacity(n_sequences: int, n_frames: int) -> None:
    """MsdnetError when the ids would not fit in 5 digits."""
    last = (n_sequences - 1) * id_stride(n_frames) + n_frames - 1
    if last > MAX_FRAME_ID:
        raise MsdnetError(
            None,
            f"{n_sequences} sequences x {n_frames} frames need frame id {last}, more than {MAX_FRAME_ID}",
        )


def prepare_output(out: Path, overwrite: bool) -> None:
    """Create ``out``; refuse a non-empty one unless ``overwrite`` (which removes only what a
    previous simulation wrote there: lidar/, radar/, sequences.json)."""
    if out.exists() and not out.is_dir():
        raise MsdnetError(out, "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise MsdnetError(out, "folder is not empty (pass --overwrite to replace it)")
        for name in MANAGED:
            target = out / name
            if target.is_symlink() or target.is_file():
                target.unlink()
            elif target.is_dir():
                shutil.rmtree(target)
    out.mkdir(parents=True, exist_ok=True)


def _write_bytes(path: Path, data: bytes) -> None:
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)


def _row(values: np.ndarray) -> str:
    flat = np.asarray(values, dtype=np.float64).ravel() + 0.0  # + 0.0: no "-0.000"
    return " ".join(f"{v:.12f}" for v in flat)


def calib_text(sensor_to_camera: np.ndarray) -> str:
    """KITTI calib file: P0..P3 (3x4), R0_rect (3x3), Tr_velo_to_cam (3x4), Tr_imu_to_velo."""
    f, cx, cy = rig.INTRINSICS
    p = np.array([[f, 0.0, cx, 0.0], [0.0, f, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
    lines = [f"P{k}: {_row(p)}" for k in range(4)]
    lines.append(f"R0_rect: {_row(np.eye(3))}")
    lines.append(f"Tr_velo_to_cam: {_row(sensor_to_camera[:3, :])}")
    lines.append("Tr_imu_to_velo:")
    return "\n".join(lines) + "\n"


def pose_text(poses: dict[str, np.ndarray]) -> str:
    """Three JSON documents, one per line, in VoD's order."""
    order = ("odomToCamera", "mapToCamera", "UTMToCamera")
    docs = [json.dumps({k: [float(v) for v in poses[k].ravel()]}, sort_keys=True) for k in order]
    return "\n".join(docs) + "\n"


class VodWriter:
    """Writes frames and split files under one output folder."""

    def __init__(self, out: Path, mounting: rig.Rig = rig.VOD) -> None:
        self.out = out
        self.calib = {
            "lidar": calib_text(rig.lidar_to_camera(mounting)).encode(),
            "radar": calib_text(rig.radar_to_camera(mounting)).encode(),
        }

    def write_frame(
        self, fid: str, lidar: np.ndarray, radar: np.ndarray, poses: dict[str, np.ndarray]
    ) -> None:
        """lidar: (N, 4) float32 [x, y, z, intensity]; radar: (M, 7) float32 VoD radar rows."""
        pose = pose_text(poses).encode()
        clouds = {"lidar": lidar, "radar": radar}
        for sensor in SENSORS:
            base = self.out / sensor / "training"
            data = np.ascontiguousarray(clouds[sensor], dtype="<f4").tobytes()
            _write_bytes(base / "velodyne" / f"{fid}.bin", data)
            _write_bytes(base / "calib" / f"{fid}.txt", self.calib[sensor])
            _write_bytes(base / "pose" / f"{fid}.json", pose)

    def write_splits(self, train: Sequence[str], val: Sequence[str]) -> None:
        """ImageSets train / val / full under lidar/ and radar/."""
        full = sorted([*train, *val])
        for sensor in SENSORS:
            for name, ids in (("train", train), ("val", val), ("full", full)):
                text = "".join(f"{i}\n" for i in ids)
                _write_bytes(self.out / sensor / "ImageSets" / f"{name}.txt", text.encode())

    def write_sequences(self, doc: dict) -> None:
        """sequences.json, sorted keys."""
        text = json.dumps(doc, sort_keys=True, indent=1) + "\n"
        _write_bytes(self.out / "sequences.json", text.encode())
