"""Seeded training augmentation, applied identically to the radar and the LiDAR of one frame.

Astyx has 440 frames from a few drives: without augmentation the lite student fits its training
frames (CD 0.86 m) and not the held-out ones (1.43 m), and the sparse scans of a drive are never
seen often enough. Each frame drawn for training gets, with its own generator:

- a mirror in y (``y -> -y``) with probability ``mirror_p`` (the radial velocity is unchanged);
- a yaw about the sensor's z axis, uniform in ``[-yaw_deg, yaw_deg]``, after which both clouds
  are cropped again as preprocessing crops them (radar to the grid, LiDAR to the grid and the
  radar's field of view), so they look like a real frame;
- a common scale of x, y, z, uniform in ``[1 - scale, 1 + scale]``;
- with probability ``dropout_p``, radar point dropout: each radar point kept with a probability
  drawn uniformly in ``[keep_min, 1]`` (a frame keeps at least one point).

Velocity / magnitude columns are left as they are. Point columns: x, y, z are the first three of
both clouds (``ModelConfig.radar_columns`` / ``lidar_columns`` start with them).
"""

from __future__ import annotations

import numpy as np

from msdnet.runtime.io.datasets.preprocess import crop_mask
from msdnet.runtime.spec.grid import GridConfig
from msdnet.training.config import AugmentConfig


def augment_pair(
    radar: np.ndarray,
    lidar: np.ndarray,
    grid: GridConfig,
    cfg: AugmentConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """One random transform of a preprocessed pair.

    radar: (N, Cr) float32 [x, y, z, ...]; lidar: (M, Cl) float32 [x, y, z, ...], radar frame.
    Returns new arrays (the inputs, which a dataset may cache, are not modified). The draws are
    made in a fixed order whatever is enabled, so a seed means the same transform.
    """
    mirror = rng.random() < cfg.mirror_p
    yaw = np.deg2rad(rng.uniform(-cfg.yaw_deg, cfg.yaw_deg))
    scale = 1.0 + rng.uniform(-cfg.scale, cfg.scale)
    thin = rng.random() < cfg.dropout_p
    keep_p = rng.uniform(cfg.keep_min, 1.0)
    keep_u = rng.random(len(radar))
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) * scale  # (3, 3) yaw then scale
    if mirror:
        rot = rot @ np.diag([1.0, -1.0, 1.0])  # mirror first

    def move(points: np.ndarray, fov: bool) -> np.ndarray:
        out = points.copy()
        out[:, :3] = (points[:, :3].astype(np.float64) @ rot.T).astype(np.float32)
        return out[crop_mask(out[:, :3], grid, fov=fov)]

    radar_out = move(radar, fov=False)  # as preprocessing crops radar: grid only
    if len(radar_out) == 0:  # everything moved out of the grid: keep the frame as it was
        return radar.copy(), lidar.copy()
    if thin and len(radar_out) > 1:
        keep = keep_u[: len(radar_out)] < keep_p
        if not keep.any():
            keep[int(np.argmin(keep_u[: len(radar_out)]))] = True
        radar_out = radar_out[keep]
    return np.ascontiguousarray(radar_out), np.ascontiguousarray(move(lidar, fov=True))
