"""The voxel grid: one frozen config per preset, shared by training, export and runtime.

Frame: radar frame, metres, x forward, y left, z up. Dense voxel tensors are laid out
``(D, H, W) = (Z, Y, X)`` and voxel coordinates are ``[z, y, x]`` (OpenPCDet order).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GridConfig:
    """A box in the radar frame cut into equal voxels."""

    point_range: tuple[float, float, float, float, float, float]  # [x0, y0, z0, x1, y1, z1] m
    voxel_size: tuple[float, float, float]  # [vx, vy, vz] m
    fov_deg: float = 60.0  # half-angle of the radar's horizontal field of view, degrees

    def __post_init__(self) -> None:
        """ValueError unless the box has six finite bounds with hi > lo, the voxel sizes are
        three finite values > 0 that cut it into at least one voxel per axis, and 0 < fov <= 180."""
        rng = np.asarray(self.point_range, dtype=np.float64)
        size = np.asarray(self.voxel_size, dtype=np.float64)
        if rng.shape != (6,) or not np.all(np.isfinite(rng)) or np.any(rng[3:] <= rng[:3]):
            raise ValueError(
                f"point_range must be [x0 y0 z0 x1 y1 z1] with x1 > x0 etc., got {self.point_range}"
            )
        if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
            raise ValueError(f"voxel_size must be three finite values > 0, got {self.voxel_size}")
        if np.any(np.round((rng[3:] - rng[:3]) / size) < 1):
            raise ValueError(f"voxel_size {self.voxel_size} is larger than the box {self.point_range}")
        if not 0.0 < float(self.fov_deg) <= 180.0:
            raise ValueError(f"fov_deg must be in (0, 180], got {self.fov_deg}")

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        """Voxels along x, y, z."""
        lo = np.asarray(self.point_range[:3], dtype=np.float64)
        hi = np.asarray(self.point_range[3:], dtype=np.float64)
        n = np.round((hi - lo) / np.asarray(self.voxel_size, dtype=np.float64)).astype(int)
        return int(n[0]), int(n[1]), int(n[2])

    @property
    def shape_zyx(self) -> tuple[int, int, int]:
        """Dense tensor shape ``(D, H, W)``."""
        x, y, z = self.shape_xyz
        return z, y, x

    def voxel_centres(self, coords_zyx: np.ndarray) -> np.ndarray:
        """coords: (V, 3) int [z, y, x] -> (V, 3) float32 [x, y, z] voxel centres in metres."""
        c = np.asarray(coords_zyx)[:, ::-1].astype(np.float64)  # (V, 3) [x, y, z] indices
        lo = np.asarray(self.point_range[:3], dtype=np.float64)
        size = np.asarray(self.voxel_size, dtype=np.float64)
        return (lo + (c + 0.5) * size).astype(np.float32)


GRID_PRESETS: dict[str, GridConfig] = {
    # tests: 32 x 32 x 10, seconds
    "tiny": GridConfig((0.0, -6.4, -2.0, 12.8, 6.4, 4.0), (0.4, 0.4, 0.6)),
    # trains on a 2-core CPU: 160 x 160 x 20
    "lite": GridConfig((0.0, -16.0, -2.0, 32.0, 16.0, 4.0), (0.2, 0.2, 0.3)),
    # the paper's VoD setting: 320 x 320 x 40
    "paper": GridConfig((0.0, -16.0, -2.0, 32.0, 16.0, 4.0), (0.1, 0.1, 0.15)),
}
