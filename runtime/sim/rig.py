"""The simulated vehicle's sensor rig: LiDAR, radar and camera mountings, as in VoD.

Frames (all right-handed, metres):
- vehicle: origin on the ground under the LiDAR, x forward, y left, z up;
- LiDAR: 1.8 m above the vehicle origin, axes as the vehicle's;
- radar: 2.5 m ahead of and 1.15 m below the LiDAR (radar-to-LiDAR translation
  (2.50, 0.06, -1.15) m, like VoD's (2.514, 0.061, -1.153)), turned by a fraction of a degree;
- camera: KITTI camera axes (x right, y down, z forward), pitched 6.8 degrees up (as VoD's
  camera is with respect to its LiDAR), near the LiDAR.
``Tr_velo_to_cam`` of each calib file maps that sensor's frame into the camera frame.

A second rig, ``ASTYX`` (``msdnet-data simulate --rig astyx``), mounts the sensors as the
Astyx HiRes2019 car does (measured from its ``calibration/*.json`` and the LiDAR's ground
ring): a Velodyne VLP-16 1.62 m above the ground (its -15 degree beam meets the road ~6 m
ahead, as in the real sweeps) and the Astyx 6455 radar 0.13 m ahead of and 0.12 m below it,
turned as in the published ``T_to_ref_COS``. Every function below takes the rig (default: VoD).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LIDAR_HEIGHT = 1.8  # m, LiDAR origin above the ground
RADAR_IN_LIDAR = (2.50, 0.06, -1.15)  # m, radar origin in the LiDAR frame
RADAR_RPY_DEG = (0.15, -0.5, 0.35)  # roll, pitch, yaw of the radar in the LiDAR frame, degrees
CAMERA_IN_LIDAR = (0.95, 0.14, -0.35)  # m, camera origin in the LiDAR frame
CAMERA_PITCH_DEG = -6.8  # camera nose-down pitch, degrees (negative: looks up, like VoD's)
INTRINSICS = (1495.0, 960.0, 625.0)  # f, cx, cy in pixels (P0..P3)


@dataclass(frozen=True)
class Rig:
    """Sensor mountings of one simulated vehicle (frames as in the module docstring)."""

    name: str  # "vod" or "astyx"
    lidar_height: float  # m, LiDAR origin above the ground
    radar_in_lidar: tuple[float, float, float]  # m, radar origin in the LiDAR frame
    radar_rpy_deg: tuple[float, float, float]  # roll, pitch, yaw of the radar in the LiDAR frame
    camera_in_lidar: tuple[float, float, float]  # m, camera origin in the LiDAR frame
    camera_pitch_deg: float  # camera pitch about the LiDAR y axis, degrees


VOD = Rig("vod", LIDAR_HEIGHT, RADAR_IN_LIDAR, RADAR_RPY_DEG, CAMERA_IN_LIDAR, CAMERA_PITCH_DEG)
# Astyx: inv(T_to_ref_COS of lidar_vlp16) = radar in LiDAR: t (0.129, -0.002, -0.121) m,
# roll / pitch / yaw (3.69, 2.02, 2.78) degrees; the camera sits 4 cm behind the radar.
ASTYX = Rig("astyx", 1.62, (0.129, -0.002, -0.121), (3.69, 2.02, 2.78), (0.09, 0.0, -0.11), 0.0)
RIGS: dict[str, Rig] = {"vod": VOD, "astyx": ASTYX}


def rot_z(yaw: float) -> np.ndarray:
    """(3, 3) rotation about z by ``yaw`` rad."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) rotation Rz(yaw) @ Ry(pitch) @ Rx(roll), angles in rad."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return rot_z(yaw) @ ry @ rx


def homogeneous(rot: np.ndarray, trans) -> np.ndarray:
    """(4, 4) transform from a (3, 3) rotation and a (3,) translation."""
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = trans
    return t


def lidar_in_vehicle(rig: Rig = VOD) -> np.ndarray:
    """(4, 4) T_vehicle<-lidar."""
    return homogeneous(np.eye(3), (0.0, 0.0, rig.lidar_height))


def radar_in_lidar(rig: Rig = VOD) -> np.ndarray:
    """(4, 4) T_lidar<-radar."""
    return homogeneous(rot_rpy(*np.radians(rig.radar_rpy_deg)), rig.radar_in_lidar)


def camera_in_lidar(rig: Rig = VOD) -> np.ndarray:
    """(4, 4) T_lidar<-camera: camera axes x right, y down, z forward."""
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: cam axes
    pitch = rot_rpy(0.0, np.radians(rig.camera_pitch_deg), 0.0)  # about the LiDAR y axis
    return homogeneous(pitch @ base, rig.camera_in_lidar)


def lidar_to_camera(rig: Rig = VOD) -> np.ndarray:
    """(4, 4) T_cam<-lidar, the LiDAR calib's ``Tr_velo_to_cam``."""
    return np.linalg.inv(camera_in_lidar(rig))


def radar_to_camera(rig: Rig = VOD) -> np.ndarray:
    """(4, 4) T_cam<-radar, the radar calib's ``Tr_velo_to_cam``."""
    return lidar_to_camera(rig) @ radar_in_lidar(rig)


def vehicle_pose(x: float, y: float, yaw: float) -> np.ndarray:
    """(4, 4) T_world<-vehicle for a vehicle on flat ground."""
    return homogeneous(rot_z(yaw), (x, y, 0.0))


def camera_pose(vehicle: np.ndarray, rig: Rig = VOD) -> np.ndarray:
    """(4, 4) T_world<-camera from T_world<-vehicle."""
    return vehicle @ lidar_in_vehicle(rig) @ camera_in_lidar(rig)
