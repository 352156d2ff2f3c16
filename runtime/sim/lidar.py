"""LiDAR model: a spinning scanner ray-cast against the scene, HDL-64-like or VLP-16-like.

- Beams (HDL-64, the VoD rig's default): 32 upper lasers from +2.0 to -8.33 degrees and 32 lower
  ones from -8.83 to -24.9 degrees; one column every ``azimuth_step_deg`` over 360 degrees.
  ``VLP16`` (the Astyx rig's): 16 lasers from +15 to -15 degrees, 2 degrees apart, one column
  every 0.2 degrees (10 Hz), 100 m range.
- Range: ``min_range`` to ``max_range``; Gaussian range noise (``range_noise`` m); a fraction
  ``dropout`` of returns lost at random, plus weak far returns (intensity under a floor that
  grows with range).
- Intensity (0..255, like VoD's ``reflectance``): material reflectivity x (0.25 + 0.75 cos i)
  with i the incidence angle, a mild range fall-off, multiplicative speckle noise.
Output rows are in the LiDAR frame: float32 ``x y z intensity``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msdnet.runtime.sim import materials as mt
from msdnet.runtime.sim.raycast import build_sectors, cast_rays, hit_materials


@dataclass(frozen=True)
class LidarConfig:
    """Scanner geometry and noise."""

    azimuth_step_deg: float = 0.125  # degrees between columns (360 degrees scanned)
    max_range: float = 120.0  # m, farthest return
    min_range: float = 1.0  # m, nearest return
    range_noise: float = 0.02  # m, 1-sigma Gaussian range noise
    dropout: float = 0.03  # fraction of returns lost at random
    n_sectors: int = 720  # azimuth bins of the ray caster's acceleration structure
    beams_deg: tuple[float, ...] | None = None  # laser elevations, degrees, top first; None: HDL-64


# Velodyne VLP-16 (Astyx rig): 16 lasers +15 .. -15 degrees every 2 degrees, 0.2 degree columns
VLP16 = LidarConfig(
    azimuth_step_deg=0.2,
    max_range=100.0,
    min_range=0.5,
    range_noise=0.03,
    dropout=0.25,
    beams_deg=tuple(float(v) for v in np.linspace(15.0, -15.0, 16)),
)


def beam_elevations(cfg: LidarConfig | None = None) -> np.ndarray:
    """(B,) float64 elevation angles of the lasers, degrees, top to bottom (B = 64 for the HDL-64
    default, len(cfg.beams_deg) otherwise)."""
    if cfg is not None and cfg.beams_deg is not None:
        return np.asarray(cfg.beams_deg, dtype=np.float64)
    return np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.9, 32)])


def beam_directions(cfg: LidarConfig) -> np.ndarray:
    """(C * B, 3) float64 unit ray directions in the LiDAR frame, column-major (az, beam)."""
    el = np.radians(beam_elevations(cfg))  # (B,)
    az = np.radians(np.arange(0.0, 360.0, cfg.azimuth_step_deg) - 180.0)  # (C,)
    d = np.empty((len(az), len(el), 3))  # (C, B, 3)
    d[..., 0] = np.cos(az)[:, None] * np.cos(el)[None, :]
    d[..., 1] = np.sin(az)[:, None] * np.cos(el)[None, :]
    d[..., 2] = np.sin(el)[None, :]
    return d.reshape(-1, 3)


def scan(
    prims: np.ndarray,
    lidar_to_world: np.ndarray,
    dirs_lidar: np.ndarray,
    cfg: LidarConfig,
    rng: np.random.Generator,
    salt: int,
) -> np.ndarray:
    """One sweep. prims: (P, N_COLS) scene at this time; lidar_to_world: (4, 4);
    dirs_lidar: (R, 3) from :func:`beam_directions`. Returns (N, 4) float32 [x, y, z, intensity]
    in the LiDAR frame."""
    origin = np.ascontiguousarray(lidar_to_world[:3, 3])
    rot = np.ascontiguousarray(lidar_to_world[:3, :3])
    start, items, near = build_sectors(prims, origin, cfg.n_sectors, cfg.max_range)
    t, hit, cos_i = cast_rays(
        prims,
        origin,
        rot,
        dirs_lidar,
        cfg.max_range,
        start,
        items,
        near,
        mt.material_array("lidar_pass"),
        mt.material_array("lidar_free_path"),
        np.uint64(salt),
    )
    keep = np.flatnonzero(np.isfinite(t) & (t >= cfg.min_range))
    t, hit, cos_i = t[keep], hit[keep], cos_i[keep]
    mat = hit_materials(prims, hit)
    refl = mt.material_array("lidar_reflectivity")[mat]  # (N,)
    speckle = rng.lognormal(0.0, 0.25, size=len(t))
    intensity = 255.0 * refl * (0.25 + 0.75 * cos_i) * np.exp(-t / 150.0) * speckle
    rng_noisy = t + rng.normal(0.0, cfg.range_noise, size=len(t))
    lost = rng.random(len(t)) < cfg.dropout
    lost |= intensity < 4.0 * (t / 60.0) ** 2  # weak far returns fall under the noise floor
    sel = ~lost
    pts = dirs_lidar[keep[sel]] * rng_noisy[sel, None]  # (N, 3)
    out = np.empty((int(sel.sum()), 4), dtype=np.float32)
    out[:, :3] = pts
    out[:, 3] = np.clip(intensity[sel], 0.0, 255.0)
    return out
