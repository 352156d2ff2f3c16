"""The simulated vehicle's sensor rig: LiDAR, radar and camera mountings, as in VoD.

Frames (all right-handed, metres):
- vehicle: origin on the ground under the LiDAR, x forward, y left, z up;
- LiDAR: 1.8 m above the vehicle origin, axes as the vehicle's;
- radar: 2.5 m ahead of and 1.15 m below the LiDAR (radar-to-LiDAR translation
  (2.50, 0.06, -1.15) m, like VoD's (2.514, 0.061, -1.153)), turned by a fraction of a degree;
- camera: KITTI camera axes (x right, y down, z forward), pitched 6.8 degrees up (as VoD's
  camera is with respect to its LiDAR), near the LiDAR.
``Tr_velo_to_cam`` of each calib file maps that sensor's frame into the camera frame.
"""

from __future__ import annotations

import numpy as np

LIDAR_HEIGHT = 1.8  # m, LiDAR origin above the ground
RADAR_IN_LIDAR = (2.50, 0.06, -1.15)  # m, radar origin in the LiDAR frame
RADAR_RPY_DEG = (0.15, -0.5, 0.35)  # roll, pitch, yaw of the radar in the LiDAR frame, degrees
CAMERA_IN_LIDAR = (0.95, 0.14, -0.35)  # m, camera origin in the LiDAR frame
CAMERA_PITCH_DEG = -6.8  # camera nose-down pitch, degrees (negative: looks up, like VoD's)
INTRINSICS = (1495.0, 960.0, 625.0)  # f, cx, cy in pixels (P0..P3)


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


def lidar_in_vehicle() -> np.ndarray:
    """(4, 4) T_vehicle<-lidar."""
    return homogeneous(np.eye(3), (0.0, 0.0, LIDAR_HEIGHT))


def radar_in_lidar() -> np.ndarray:
    """(4, 4) T_lidar<-radar."""
    return homogeneous(rot_rpy(*np.radians(RADAR_RPY_DEG)), RADAR_IN_LIDAR)


def camera_in_lidar() -> np.ndarray:
    """(4, 4) T_lidar<-camera: camera axes x right, y down, z forward."""
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: cam axes
    pitch = rot_rpy(0.0, np.radians(CAMERA_PITCH_DEG), 0.0)  # about the LiDAR y axis
    return homogeneous(pitch @ base, CAMERA_IN_LIDAR)


def lidar_to_camera() -> np.ndarray:
    """(4, 4) T_cam<-lidar, the LiDAR calib's ``Tr_velo_to_cam``."""
    return np.linalg.inv(camera_in_lidar())


def radar_to_camera() -> np.ndarray:
    """(4, 4) T_cam<-radar, the radar calib's ``Tr_velo_to_cam``."""
    return lidar_to_camera() @ radar_in_lidar()


def vehicle_pose(x: float, y: float, yaw: float) -> np.ndarray:
    """(4, 4) T_world<-vehicle for a vehicle on flat ground."""
    return homogeneous(rot_z(yaw), (x, y, 0.0))


def camera_pose(vehicle: np.ndarray) -> np.ndarray:
    """(4, 4) T_world<-camera from T_world<-vehicle."""
    return vehicle @ lidar_in_vehicle() @ camera_in_lidar()
