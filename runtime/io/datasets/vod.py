"""View-of-Delft reader (devkit layout); the simulator writes the same layout.

Layout (``part`` is ``training``, or ``testing`` for ``split="test"`` when that folder exists)::

    lidar/<part>/{velodyne/*.bin, calib/*.txt, pose/*.json}   LiDAR: float32 x y z intensity
    radar/<part>/{velodyne/*.bin, calib/*.txt, pose/*.json}   radar: float32 x7, one scan
    radar_3frames|radar_3_scans/<part>/velodyne/*.bin       3 accumulated scans (full release)
    radar_5frames|radar_5_scans/<part>/velodyne/*.bin       5 accumulated scans (full release)
    lidar/ImageSets/{train,val,test}.txt                    split files (also radar/ or root)

Transforms: each ``calib/*.txt`` is KITTI style and its ``Tr_velo_to_cam`` maps that sensor
into the camera, so ``radar_to_lidar = inv(T_cam<-lidar) @ T_cam<-radar``. A pose file holds
``odomToCamera``, ``mapToCamera``, ``UTMToCamera`` (4x4 row-major, one JSON document per line);
as in the devkit, ``odomToCamera`` maps camera coordinates INTO the odom frame (it is
``T_odom_camera``), so the radar pose is ``odomToCamera @ T_cam<-radar``.

Multi-scan radar (``radar_frames`` = n > 1): read from the accumulated folder when one exists;
otherwise accumulated here from the n - 1 previous frames (ids ``id-1 .. id-(n-1)``), each moved
into the current radar frame with the poses, ``time`` set to ``-k`` for the scan ``k`` frames
back. ``v_r`` / ``v_r_compensated`` are kept as measured (radial directions of older scans are
not re-projected). A neighbour whose radar file or pose is missing, or that lies more than
``MAX_STEP_M`` metres per frame away (a sequence boundary), is left out, so frames at the start
of a sequence have fewer scans.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msdnet.runtime.engine.pointcloud import PointCloud, concat_clouds
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.datasets.frame import Frame, FrameDataset, as_transform, read_json, split_contiguous
from msdnet.runtime.io.files import read_cloud

MAX_STEP_M = 3.0  # farther than this per frame step (30 m/s at 10 Hz): not the same sequence
POSE_KEY = "odomToCamera"  # the pose used for ``Frame.pose`` and scan accumulation


def read_kitti_calib(path: Path, key: str = "Tr_velo_to_cam") -> np.ndarray:
    """(4, 4) float64 from one ``key: 12 numbers`` line of a KITTI calib file."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise MsdnetError(path, "calibration file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise MsdnetError(path, f"cannot read calibration ({err})") from None
    for line in lines:
        name, _, values = line.partition(":")
        if name.strip() == key:
            try:
                numbers = [float(v) for v in values.split()]
            except ValueError:
                raise MsdnetError(path, f"{key} has non-numeric values") from None
            return as_transform(numbers, path, key)
    raise MsdnetError(path, f"no {key} line")


class VodDataset(FrameDataset):
    """VoD frames: radar scan(s) and the LiDAR sweep moved into the radar frame.

    ``split``: None (every LiDAR frame), or the name of an ImageSets file (``train``, ``val``,
    ``test``); ``train`` / ``val`` without a split file fall back to ``split_contiguous``.
    ``radar_frames``: scans per radar cloud (1, or n > 1 as described in the module docstring).
    """

    def __init__(self, root: str | Path, split: str | None = None, radar_frames: int = 1) -> None:
        self.root = Path(root)
        self.split = split
        self.radar_frames = int(radar_frames)
        if not self.root.is_dir():
            raise MsdnetError(self.root, "dataset folder not found")
        if self.radar_frames < 1:
            raise MsdnetError(self.root, f"radar_frames must be >= 1, got {radar_frames}")
        testing = split == "test" and (self.root / "lidar" / "testing").is_dir()
        self.part = "testing" if testing else "training"
        self.lidar_dir = self.root / "lidar" / self.part
        self.radar_dir = self.root / "radar" / self.part
        velodyne = self.lidar_dir / "velodyne"
        if not velodyne.is_dir():
            raise MsdnetError(velodyne, "folder not found (expected the VoD devkit layout)")
        all_ids = sorted(p.stem for p in velodyne.glob("*.bin"))
        if not all_ids:
            raise MsdnetError(velodyne, "no .bin frames")
        self.frame_ids = self._split_ids(all_ids)
        self.multi_dir: Path | None = None
        self.radar_source = "single scan"
        if self.radar_frames > 1:
            for name in (f"radar_{self.radar_frames}frames", f"radar_{self.radar_frames}_scans"):
                candidate = self.root / name / self.part / "velodyne"
                if candidate.is_dir():
                    self.multi_dir = candidate
                    self.radar_source = f"accumulated folder {name}"
                    break
            else:
                self.radar_source = f"accumulated here from {self.radar_frames - 1} previous scans"
        poses = [d / "pose" for d in (self.lidar_dir, self.radar_dir)]
        self.pose_dir: Path | None = next((d for d in poses if d.is_dir()), None)

    def split_file(self, name: str) -> Path | None:
        """The published ``ImageSets/<name>.txt`` (under lidar/, radar/ or the root), if any."""
        for folder in ("lidar", "radar", "."):
            path = self.root / folder / "ImageSets" / f"{name}.txt"
            if path.is_file():
                return path
        return None

    def _split_ids(self, all_ids: list[str]) -> list[str]:
        if self.split is None:
            return all_ids
        split_file = self.split_file(self.split)
        if split_file is not None:
            try:
                text = split_file.read_text(encoding="utf-8")
            except (OSError, UnicodeDecodeError) as err:
                raise MsdnetError(split_file, f"cannot read split file ({err})") from None
            return [tok for tok in text.split() if tok]
        if self.split in ("train", "val"):
            train, val = split_contiguous(all_ids)
            return train if self.split == "train" else val
        raise MsdnetError(self.root, f"no ImageSets/{self.split}.txt under lidar/, radar/ or root")

    def radar_to_lidar(self, frame_id: str) -> np.ndarray:
        """(4, 4) float64 ``inv(T_cam<-lidar) @ T_cam<-radar`` from the two calib files."""
        t_cam_lidar = read_kitti_calib(self.lidar_dir / "calib" / f"{frame_id}.txt")
        t_cam_radar = read_kitti_calib(self._radar_calib(frame_id))
        return np.linalg.inv(t_cam_lidar) @ t_cam_radar

    def _radar_calib(self, frame_id: str) -> Path:
        path = self.radar_dir / "calib" / f"{frame_id}.txt"
        if not path.is_file() and self.multi_dir is not None:
            alt = self.multi_dir.parent / "calib" / f"{frame_id}.txt"
            if alt.is_file():
                return alt
        return path

    def camera_pose(self, frame_id: str) -> np.ndarray | None:
        """(4, 4) float64 ``T_odom<-camera`` (``odomToCamera``), None without a pose folder."""
        if self.pose_dir is None:
            return None
        path = self.pose_dir / f"{frame_id}.json"
        docs = read_json(path)
        merged: dict = {}
        for doc in docs if isinstance(docs, list) else [docs]:
            if isinstance(doc, dict):
                merged.update(doc)
        if POSE_KEY not in merged:
            raise MsdnetError(path, f"no {POSE_KEY} in pose file")
        return as_transform(merged[POSE_KEY], path, POSE_KEY)

    def pose(self, frame_id: str) -> np.ndarray | None:
        """(4, 4) float64 radar frame -> odom frame, None without a pose folder."""
        t_odom_cam = self.camera_pose(frame_id)
        if t_odom_cam is None:
            return None
        t_cam_radar = read_kitti_calib(self._radar_calib(frame_id))
        return t_odom_cam @ t_cam_radar

    def load(self, frame_id: str) -> Frame:
        r2l = self.radar_to_lidar(frame_id)
        lidar = read_cloud(self.lidar_dir / "velodyne" / f"{frame_id}.bin", kind="lidar")
        accumulate = self.multi_dir is None and self.radar_frames > 1
        has_pose = self.pose_dir is not None and (self.pose_dir / f"{frame_id}.json").is_file()
        pose = self.pose(frame_id) if accumulate or has_pose else None  # one scan needs no pose
        if self.multi_dir is not None:
            radar = read_cloud(self.multi_dir / f"{frame_id}.bin", kind="vod_radar")
        elif self.radar_frames > 1:
            radar = self._accumulate(frame_id, pose)
        else:
            radar = read_cloud(self.radar_dir / "velodyne" / f"{frame_id}.bin", kind="vod_radar")
        return Frame(frame_id, radar, lidar.transformed(np.linalg.inv(r2l)), pose, r2l)

    def _accumulate(self, frame_id: str, pose: np.ndarray | None) -> PointCloud:
        """The current scan plus up to ``radar_frames - 1`` previous ones, in this radar frame."""
        current = read_cloud(self.radar_dir / "velodyne" / f"{frame_id}.bin", kind="vod_radar")
        if pose is None:
            raise MsdnetError(
                self.root,
                f"radar_frames={self.radar_frames} needs radar_{self.radar_frames}frames/ "
                "or pose files to accumulate scans",
            )
        if not frame_id.isdigit():
            return current
        world_to_current = np.linalg.inv(pose)
        scans = [current]
        for k in range(1, self.radar_frames):
            nid = str(int(frame_id) - k).zfill(len(frame_id))
            path = self.radar_dir / "velodyne" / f"{nid}.bin"
            if int(frame_id) - k < 0 or not path.is_file():
                break
            if not (self.pose_dir / f"{nid}.json").is_file():
                break
            rel = world_to_current @ self.pose(nid)  # (4, 4) scan nid -> current radar frame
            if np.linalg.norm(rel[:3, 3]) > MAX_STEP_M * k:
                break
            scan = read_cloud(path, kind="vod_radar").transformed(rel)
            if scan.has("time"):
                scan.points[:, scan.columns.index("time")] = -float(k)
            scans.append(scan)
        return concat_clouds(scans)
