"""One simulated sequence: its properties from the seed, then paired LiDAR/radar frames with poses.

Randomness: sequence ``k`` of seed ``S`` draws its properties, street grid, trajectory and scene
from ``SeedSequence(S, spawn_key=(k,))`` and frame ``f``'s sensor noise from
``SeedSequence(S, spawn_key=(k, f + 1))``, so a sequence does not depend on how many sequences
are simulated, and the same seed gives the same bytes.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from msdnet.runtime.sim import lidar, radar, rig
from msdnet.runtime.sim.rigs import SIM_RIGS, SimRig, astyx_rows
from msdnet.runtime.sim.scene import Scene, build_scene
from msdnet.runtime.sim.trajectory import Trajectory, drive, make_grid

UTM_ORIGIN = (593_800.0, 5_762_400.0)  # m, easting / northing near Delft (UTM 31U)


@dataclass(frozen=True)
class SequenceInfo:
    """What a sequence is, for sequences.json and the benchmarks."""

    index: int  # sequence number k
    loop: bool  # planned to circle a block and pass its start again
    moving_objects: bool  # has moving cars, cyclists and pedestrians
    cruise_speed: float  # m/s, speed on straight runs
    n_moving: int  # number of moving objects in the scene
    n_primitives: int  # size of the scene


@dataclass(frozen=True)
class Frame:
    """One simulated frame: both clouds in their sensor frames, and the poses."""

    index: int  # frame number inside the sequence
    lidar: np.ndarray  # (N, 4) float32 [x, y, z, intensity], LiDAR frame
    # (M, 7) float32 [x, y, z, rcs, v_r, v_r_compensated, time], radar frame (Astyx rig:
    # column 3 holds mag and column 4 the Astyx v_r, see rigs.py)
    radar: np.ndarray
    radar_source: np.ndarray  # (M,) int8 material id of a detection, or radar.*_GHOST / CLUTTER
    vehicle_to_world: np.ndarray  # (4, 4) T_world<-vehicle (world = map frame)
    poses: dict[str, np.ndarray]  # VoD pose keys -> (4, 4) camera poses T_<key frame><-camera


class SequenceSim:
    """Builds a sequence's world once, then renders its frames one by one."""

    def __init__(
        self,
        seed: int,
        index: int,
        n_frames: int,
        lidar_cfg: lidar.LidarConfig | None = None,
        radar_cfg: radar.RadarConfig | None = None,
        sim_rig: SimRig | None = None,
    ) -> None:
        """Sequence ``index`` of ``seed``, ``n_frames`` long, on ``sim_rig`` (default: the VoD
        rig); ``lidar_cfg`` / ``radar_cfg`` override the rig's sensor models."""
        self.seed, self.index, self.n_frames = seed, index, n_frames
        self.rig: SimRig = sim_rig or SIM_RIGS["vod"]
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(index,)))
        loop = True if index == 0 else False if index == 1 else bool(rng.random() < 0.5)
        moving = True if index < 2 else bool(rng.random() < 0.7)
        cruise = float(rng.uniform(*self.rig.cruise_speed))
        busy = float(rng.uniform(0.7, 1.4))
        dist = cruise * n_frames * 0.1
        # loops: blocks small enough that circling one fits in the planned distance
        block = (35.0, float(np.clip(0.12 * dist, 40.0, 110.0))) if loop else (45.0, 110.0)
        grid = make_grid(rng, block, dist + 250.0)
        self.traj: Trajectory = drive(rng, grid, n_frames, loop, cruise)
        self.scene: Scene = build_scene(rng, grid, self.traj, moving, busy)
        yaw = float(rng.uniform(-np.pi, np.pi))
        self.utm_from_world = rig.homogeneous(
            rig.rot_z(yaw),
            (UTM_ORIGIN[0] + rng.uniform(-2e3, 2e3), UTM_ORIGIN[1] + rng.uniform(-2e3, 2e3), 0.0),
        )
        self.info = SequenceInfo(index, loop, moving, cruise, self.scene.n_moving, len(self.scene.prims))
        self.lidar_cfg = lidar_cfg or self.rig.lidar
        self.radar = radar.RadarSim(radar_cfg or self.rig.radar)
        self.lidar_dirs = lidar.beam_directions(self.lidar_cfg)
        self.odom_from_world = np.linalg.inv(self.vehicle_pose(0))

    def vehicle_pose(self, f: int) -> np.ndarray:
        """(4, 4) T_world<-vehicle at frame ``f`` (world = map frame, ground at z = 0)."""
        x, y = self.traj.xy[f]
        return rig.vehicle_pose(float(x), float(y), float(self.traj.yaw[f]))

    def frame(self, f: int) -> Frame:
        """Render frame ``f`` (0-based)."""
        fs = np.random.SeedSequence(self.seed, spawn_key=(self.index, f + 1))
        rng = np.random.default_rng(fs)
        salt = int(fs.generate_state(1, np.uint64)[0])
        prims = self.scene.at(float(self.traj.time[f]))
        vehicle = self.vehicle_pose(f)
        lidar_w = vehicle @ rig.lidar_in_vehicle(self.rig.mounting)
        radar_w = lidar_w @ rig.radar_in_lidar(self.rig.mounting)
        cloud = lidar.scan(prims, lidar_w, self.lidar_dirs, self.lidar_cfg, rng, salt)
        yaw = float(self.traj.yaw[f])
        v_vehicle = self.traj.speed[f] * np.array([np.cos(yaw), np.sin(yaw), 0.0])
        lever = radar_w[:3, 3] - vehicle[:3, 3]
        omega = float(self.traj.yaw_rate[f])
        v_radar = v_vehicle + np.array([-omega * lever[1], omega * lever[0], 0.0])
        points, source = self.radar.scan(prims, radar_w, v_radar, rng, salt ^ 0x5A5A5A5A)
        if self.rig.astyx_columns:
            points = astyx_rows(points, self.radar)
        cam_w = rig.camera_pose(vehicle, self.rig.mounting)
        poses = {  # as in VoD, "xToCamera" is the camera pose in x: T_x<-camera
            "odomToCamera": self.odom_from_world @ cam_w,
            "mapToCamera": cam_w,
            "UTMToCamera": self.utm_from_world @ cam_w,
        }
        return Frame(f, cloud, points, source, vehicle, poses)

    def frames(self) -> Iterator[Frame]:
        """All frames in order."""
        for f in range(self.n_frames):
            yield self.frame(f)
