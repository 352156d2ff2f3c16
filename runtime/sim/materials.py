"""Materials of the simulated scene: how each one answers a LiDAR beam and a radar wave.

Every primitive of a scene carries a material id (column ``MAT`` of the primitive table). The
table below is the single place the sensor models read material behaviour from; the radar model
in :mod:`msdnet.runtime.sim.radar` documents how the radar columns are used.

The radar values are effective ones: they fold in what the model leaves out (antenna gains,
processing losses) and were tuned so that simulated scans land in the VoD statistics bands
(``msdnet.runtime.io.datasets.stats``). Their ordering is the physical one: per unit area at normal
incidence, metal (13.5 dB diffuse, +37.5 dB specular lobe) >> facade (4.5) > vegetation (1.5)
> people (-6.5) >> asphalt (-12.5, and nearly always seen at grazing incidence).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# material ids (row index in MATERIALS)
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
    Material("asphalt", 0.3, 0.0, 0.0, -12.5, -35.5, 3.0, 0.0, 0.0, 0.0),
    Material("concrete", 0.45, 0.0, 0.0, -1.5, 8.5, 4.0, 0.0, 0.0, 0.02),
    Material("facade", 0.55, 0.0, 0.0, 4.5, 12.5, 5.0, 0.0, 0.0, 0.08),
    Material("glass", 0.1, 0.0, 0.0, -0.5, 18.5, 3.0, 0.0, 0.0, 0.08),
    Material("metal", 0.7, 0.0, 0.0, 13.5, 37.5, 8.0, 0.0, 0.0, 0.3),
    Material("vegetation", 0.5, 0.0, 0.7, 1.5, -55.5, 1.0, 0.0, 2.0, 0.02),
    Material("wood", 0.45, 0.0, 0.0, 1.5, 6.5, 6.0, 0.0, 0.0, 0.0),
    Material("human", 0.4, 0.0, 0.0, -6.5, -1.0, 10.0, 0.0, 0.0, 0.0),
    Material("fence", 0.6, 0.55, 0.0, 6.5, 20.5, 4.0, 0.35, 0.0, 0.2),
    Material("sign", 1.0, 0.0, 0.0, 10.5, 34.5, 5.0, 0.0, 0.0, 0.0),
)

GLINT_CELL = 0.6  # m, edge of the world-fixed cubes that may hold a glint (radar.py, step 2)

N_MATERIALS = len(MATERIALS)


def material_array(attr: str) -> np.ndarray:
    """One attribute of every material, indexed by material id: (N_MATERIALS,) float64."""
    return np.array([getattr(m, attr) for m in MATERIALS], dtype=np.float64)
