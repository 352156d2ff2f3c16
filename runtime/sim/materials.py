"""Materials of the simulated scene: how each one answers a LiDAR beam and a radar wave.

Every primitive of a scene carries a material id (column ``MAT`` of the primitive table). The
table below is the single place where the sensor models read material behaviour from; the radar
model in :mod:`msdnet.runtime.sim.radar` documents how the radar columns are used.

Radar ordering (diffuse backscatter per unit area at normal incidence; metal also has a strong
specular lobe): metal >> facade > vegetation > concrete, glass > human >> asphalt (grazing).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ASPHALT = 0
CONCRETE = 1
FACADE = 2
GLASS = 3
METAL = 4
VEGETATION = 5
WOOD = 6
HUMAN = 7
FENCE = 8
SIGN = 9


@dataclass(frozen=True)
class Material:
    """Sensor response of one surface type."""

    name: str  # label, for logs and docs
    lidar_reflectivity: float  # diffuse LiDAR reflectivity in [0, 1] (intensity 255 at 1)
    lidar_pass: float  # probability a LiDAR ray passes a mesh surface (fences, 0 when solid)
    lidar_free_path: float  # m, mean free path inside a volumetric material (0 = solid surface)
    radar_diffuse_db: float  # dB m^2/m^2, diffuse backscatter per unit area at normal incidence
    radar_specular_db: float  # dB m^2/m^2, specular lobe per unit area at normal incidence
    radar_lobe_deg: float  # width (1/e) of the specular lobe, degrees of incidence
    radar_pass: float  # probability a radar ray passes a mesh surface
    radar_free_path: float  # m, mean free path of the radar wave inside a volumetric material
    radar_glint_density: float  # share of GLINT_CELL cells of the surface holding a glint


MATERIALS: tuple[Material, ...] = (
    Material("asphalt", 0.22, 0.0, 0.0, -7.5, -30.5, 3.0, 0.0, 0.0, 0.0),
    Material("concrete", 0.35, 0.0, 0.0, 3.5, 13.5, 4.0, 0.0, 0.0, 0.02),
    Material("facade", 0.45, 0.0, 0.0, 9.5, 17.5, 5.0, 0.0, 0.0, 0.08),
    Material("glass", 0.08, 0.0, 0.0, 4.5, 23.5, 3.0, 0.0, 0.0, 0.08),
    Material("metal", 0.55, 0.0, 0.0, 15.5, 39.5, 8.0, 0.0, 0.0, 0.3),
    Material("vegetation", 0.4, 0.0, 0.7, 6.5, -50.5, 1.0, 0.0, 2.0, 0.02),
    Material("wood", 0.35, 0.0, 0.0, 6.5, 11.5, 6.0, 0.0, 0.0, 0.0),
    Material("human", 0.3, 0.0, 0.0, 2.5, 12.5, 10.0, 0.0, 0.0, 0.0),
    Material("fence", 0.5, 0.55, 0.0, 11.5, 25.5, 4.0, 0.35, 0.0, 0.2),
    Material("sign", 0.98, 0.0, 0.0, 15.5, 39.5, 5.0, 0.0, 0.0, 0.0),
)

GLINT_CELL = 0.6  # m, edge of the world-fixed cubes that may hold a glint (radar.py, step 2)

N_MATERIALS = len(MATERIALS)


def material_array(attr: str) -> np.ndarray:
    """One attribute of every material, indexed by material id: (N_MATERIALS,) float64."""
    return np.array([getattr(m, attr) for m in MATERIALS], dtype=np.float64)
