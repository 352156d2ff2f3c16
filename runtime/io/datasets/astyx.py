"""Astyx HiRes2019 reader: the radar is the reference frame.

Layout::

    dataset.json                  {"data": {"0": {"radar_6455": ..., "lidar_vlp16": ...,
                                  "calibration": ...}, ...}} (paths relative to the root)
    radar_6455/NNNNNN.txt         a blank line, ``X Y Z V_r Mag``, one detection per line
    lidar_vlp16/NNNNNN.txt        ``X Y Z Reflectivity LaserID Timestamp`` (Velodyne VLP-16)
    calibration/NNNNNN.json       {"sensors": [{"sensor_uid": ..., "calib_data":
                                  {"T_to_ref_COS": 4x4}}, ...]}
    groundtruth_obj3d/NNNNNN.json 3D object boxes, radar frame (``astyx_boxes``; optional)

``T_to_ref_COS`` maps a sensor's points into the reference coordinate system (the radar's;
its own matrix is the identity), so ``p_radar = inv(T_radar) @ T_lidar @ p_lidar`` and
``radar_to_lidar = inv(T_lidar) @ T_radar``. There are no poses (``Frame.pose`` is None).
Without ``dataset.json`` the frames are the ``radar_6455/*.txt`` files with the same stems in
the other folders. Radar ``v_r`` is relative (not ego-compensated); ``mag`` is not RCS.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.datasets.astyx_boxes import BOXES_DIR, Boxes, empty_boxes, read_astyx_boxes
from msdnet.runtime.io.datasets.frame import Frame, FrameDataset, as_transform, read_json, split_contiguous
from msdnet.runtime.io.files import read_cloud

RADAR_UID = "radar_6455"
LIDAR_UID = "lidar_vlp16"
CALIB_UID = "calibration"


class AstyxDataset(FrameDataset):
    """Astyx frames; ``split`` None (all), or ``train`` / ``val`` by ``split_contiguous``."""

    def __init__(self, root: str | Path, split: str | None = None, val_fraction: float = 0.2) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise MsdnetError(self.root, "dataset folder not found")
        self.files: dict[str, dict[str, Path]] = self._index()
        ids = sorted(self.files, key=lambda s: (len(s), s))
        if split is None:
            self.frame_ids = ids
        elif split in ("train", "val"):
            train, val = split_contiguous(ids, val_fraction)
            self.frame_ids = train if split == "train" else val
        else:
            raise MsdnetError(self.root, f"unknown Astyx split {split!r} (train, val or none)")
        self.split = split

    def _index(self) -> dict[str, dict[str, Path]]:
        """frame id -> {sensor uid: file} from dataset.json (or the radar folder without it)."""
        manifest = self.root / "dataset.json"
        files: dict[str, dict[str, Path]] = {}
        if manifest.is_file():
            doc = read_json(manifest)
            data = doc.get("data") if isinstance(doc, dict) else None
            if not isinstance(data, dict):
                raise MsdnetError(manifest, "no 'data' object")
            for key, entry in data.items():
                if not isinstance(entry, dict) or not all(
                    isinstance(entry.get(uid), str) for uid in (RADAR_UID, LIDAR_UID, CALIB_UID)
                ):
                    raise MsdnetError(manifest, f"entry {key!r} lacks radar/lidar/calibration")
                paths = {uid: self.root / entry[uid] for uid in (RADAR_UID, LIDAR_UID, CALIB_UID)}
                files[paths[RADAR_UID].stem] = paths
        else:
            radar_dir = self.root / RADAR_UID
            if not radar_dir.is_dir():
                raise MsdnetError(manifest, "neither dataset.json nor radar_6455/ found")
            for radar in radar_dir.glob("*.txt"):
                files[radar.stem] = {
                    RADAR_UID: radar,
                    LIDAR_UID: self.root / LIDAR_UID / radar.name,
                    CALIB_UID: self.root / CALIB_UID / f"{radar.stem}.json",
                }
        if not files:
            raise MsdnetError(self.root, "no Astyx frames found")
        return files

    def sensor_transforms(self, frame_id: str) -> dict[str, np.ndarray]:
        """sensor uid -> (4, 4) float64 ``T_to_ref_COS`` (sensor -> radar) from the calib JSON."""
        path = self.files[frame_id][CALIB_UID]
        doc = read_json(path)
        sensors = doc.get("sensors") if isinstance(doc, dict) else None
        if not isinstance(sensors, list):
            raise MsdnetError(path, "no 'sensors' list")
        out: dict[str, np.ndarray] = {}
        for sensor in sensors:
            calib = sensor.get("calib_data", {}) if isinstance(sensor, dict) else {}
            if isinstance(calib, dict) and "T_to_ref_COS" in calib:
                uid = str(sensor.get("sensor_uid"))
                out[uid] = as_transform(calib["T_to_ref_COS"], path, f"{uid} T_to_ref_COS")
        for uid in (RADAR_UID, LIDAR_UID):
            if uid not in out:
                raise MsdnetError(path, f"no T_to_ref_COS for {uid}")
        return out

    def radar_to_lidar(self, frame_id: str) -> np.ndarray:
        """(4, 4) float64 ``inv(T_lidar) @ T_radar``."""
        t = self.sensor_transforms(frame_id)
        return np.linalg.inv(t[LIDAR_UID]) @ t[RADAR_UID]

    def boxes(self, frame_id: str) -> Boxes:
        """The frame's labelled 3D boxes, radar frame (``astyx_boxes``); no box when the frame has
        no ``groundtruth_obj3d`` file. ``has_boxes`` says whether the folder holds labels at all."""
        path = self.root / BOXES_DIR / f"{frame_id}.json"
        return read_astyx_boxes(path) if path.is_file() else empty_boxes()

    @property
    def has_boxes(self) -> bool:
        """Whether the dataset folder holds object labels (``groundtruth_obj3d/``)."""
        return (self.root / BOXES_DIR).is_dir()

    def load(self, frame_id: str) -> Frame:
        r2l = self.radar_to_lidar(frame_id)
        radar = read_cloud(self.files[frame_id][RADAR_UID])
        lidar = read_cloud(self.files[frame_id][LIDAR_UID])
        lidar_radar = lidar.transformed(np.linalg.inv(r2l))
        return Frame(frame_id, radar, lidar_radar, None, r2l, lidar_rig="vlp16")
