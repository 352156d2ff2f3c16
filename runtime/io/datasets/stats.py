"""Realism statistics of a radar + LiDAR dataset (DESIGN.md section 2), real or simulated.

Measured on raw frames (before preprocessing), in the radar frame. "Region" is the grid box of
``grid`` (default: the paper grid) intersected with ``|azimuth| <= grid.fov_deg``. LiDAR is
counted with its ground. Radar range, RCS, z and motion are pooled over all radar points of
all frames (not only the region). ``REALISM_TARGETS`` holds the bands DESIGN.md gives from the
three real VoD example frames; the "about" figures are read as the bands noted beside them.
``ASTYX_TARGETS`` holds bands around the figures of the 440 real Astyx HiRes2019 frames
(``msdnet-data stats --dataset astyx``), which the simulator's Astyx rig aims at
(docs/sim-astyx-rig.md); ``TARGETS`` names both sets.

Beyond DESIGN.md's list: per-frame radar count percentiles, azimuth / elevation spread (degrees,
``atan2(y, x)`` and ``asin(z / r)``), the magnitude (``mag``, Astyx) and radial-speed (``v_r``)
distributions, and the LiDAR count in the radar's field of view (``x > 0``, ``|azimuth| <=
FOV_AZ_DEG``, horizontal range ``<= FOV_RANGE_M``, ground kept: the region the Astyx sample
keeps of its LiDAR).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, fields

import numpy as np

from msdnet.runtime.io.datasets.frame import Frame
from msdnet.runtime.io.datasets.preprocess import crop_mask
from msdnet.runtime.spec.grid import GRID_PRESETS, GridConfig

MOVING_SPEED = 0.5  # m/s: |v_r_compensated| above this counts as moving
FOV_AZ_DEG = 60.0  # degrees, half azimuth of the region ``lidar_in_fov`` counts
FOV_RANGE_M = 60.0  # m, horizontal range of that region

# statistic -> (low, high) band; from DESIGN.md section 2 (VoD, single scan, radar frame)
REALISM_TARGETS: dict[str, tuple[float, float]] = {
    "radar_points": (240.0, 350.0),  # "240-350 radar points per frame"
    "radar_in_region": (110.0, 220.0),  # "~160 of them inside the paper grid and +-60 deg"
    "lidar_in_region": (25_000.0, 60_000.0),  # "~40k points with ground"
    # "~100-250x the radar"; upper end 300 because real frame 01047 alone measures 291
    "lidar_radar_ratio": (100.0, 300.0),
    "range_median": (18.0, 34.0),  # m
    "range_p90": (47.0, 78.0),  # m
    "rcs_median": (-15.0, -10.0),  # dBsm
    "rcs_p10": (-35.0, -25.0),  # dBsm, "about -30"
    "rcs_p90": (0.0, 8.0),  # dBsm
    "z_p5": (-3.5, -1.5),  # m, "about -2.5"
    "z_p95": (3.5, 6.5),  # m, "about +5"
    "moving_share": (0.05, 0.30),  # "~15 % moving"
}

# statistic -> (low, high) band around the 440 real Astyx HiRes2019 frames (radar frame); the
# measured value is in the comment
ASTYX_TARGETS: dict[str, tuple[float, float]] = {
    "radar_points": (1500.0, 3000.0),  # 2217 mean per frame (per-frame 5th-95th: 858-4098)
    "radar_in_region": (550.0, 1100.0),  # 808
    "lidar_in_region": (3500.0, 6500.0),  # 4820, VLP-16 with ground
    "lidar_radar_ratio": (4.0, 9.0),  # 5.96: the LiDAR is barely denser than this radar
    "range_median": (28.0, 43.0),  # 35.4 m
    "range_p90": (62.0, 88.0),  # 75.2 m
    "z_p5": (-3.5, -1.5),  # -2.76 m
    "z_p95": (5.0, 9.0),  # 6.93 m
    "azimuth_p5": (-58.0, -45.0),  # -52.1 degrees
    "azimuth_p95": (45.0, 58.0),  # 51.8 degrees
    "elevation_p5": (-8.0, -3.5),  # -5.46 degrees
    "elevation_p95": (5.0, 10.0),  # 7.61 degrees
    "mag_median": (48.5, 53.0),  # 50.5 (dB, floor 45)
    "mag_p10": (45.0, 47.5),  # 46.0
    "mag_p90": (57.5, 65.0),  # 61.5
    "vr_p5": (-5.3, -3.5),  # -4.71 m/s (folded into about +-5.3 m/s)
    "vr_p95": (3.5, 5.3),  # 4.63 m/s
    "lidar_in_fov": (4500.0, 8000.0),  # 6171 per frame
}
TARGETS: dict[str, dict[str, tuple[float, float]]] = {"vod": REALISM_TARGETS, "astyx": ASTYX_TARGETS}


@dataclass(frozen=True)
class RealismStats:
    """Statistics over ``frames`` frames; None where the radar lacks the column."""

    frames: int  # frames measured
    radar_points: float  # mean radar points per frame
    radar_in_region: float  # mean radar points per frame inside the grid box and the FOV
    lidar_in_region: float  # mean LiDAR points per frame in the same region (ground kept)
    lidar_radar_ratio: float  # total LiDAR in region / total radar in region
    range_median: float  # m, median 3D range of all radar points
    range_p90: float  # m, 90th percentile of the radar range
    rcs_median: float | None  # dBsm, median RCS (None without an ``rcs`` column)
    rcs_p10: float | None  # dBsm, 10th percentile of RCS
    rcs_p90: float | None  # dBsm, 90th percentile of RCS
    z_p5: float  # m, 5th percentile of radar z
    z_p95: float  # m, 95th percentile of radar z
    moving_share: float | None  # share of radar points with |v_r_compensated| > MOVING_SPEED
    radar_points_p5: float  # 5th percentile over frames of the radar points per frame
    radar_points_p95: float  # 95th percentile over frames of the radar points per frame
    azimuth_p5: float  # degrees, 5th percentile of the radar azimuth atan2(y, x)
    azimuth_p95: float  # degrees, 95th percentile of the radar azimuth
    elevation_p5: float  # degrees, 5th percentile of the radar elevation asin(z / r)
    elevation_p50: float  # degrees, median radar elevation
    elevation_p95: float  # degrees, 95th percentile of the radar elevation
    mag_median: float | None  # median radar magnitude (None without a ``mag`` column)
    mag_p10: float | None  # 10th percentile of the magnitude
    mag_p90: float | None  # 90th percentile of the magnitude
    vr_p5: float | None  # m/s, 5th percentile of the measured v_r (None without ``v_r``)
    vr_p95: float | None  # m/s, 95th percentile of the measured v_r
    lidar_in_fov: float  # mean LiDAR points per frame with x > 0, |az| <= FOV_AZ_DEG, <= FOV_RANGE_M

    def out_of_band(self, targets: dict[str, tuple[float, float]] | None = None) -> list[str]:
        """Names of statistics outside their target band (statistics that are None skipped)."""
        bands = REALISM_TARGETS if targets is None else targets
        bad = []
        for name, (lo, hi) in bands.items():
            value = getattr(self, name)
            if value is not None and not lo <= value <= hi:
                bad.append(name)
        return bad


def compute_stats(frames: Iterable[Frame], grid: GridConfig | None = None) -> RealismStats:
    """Realism statistics of raw frames (radar frame); needs at least one frame."""
    grid = grid or GRID_PRESETS["paper"]
    n_frames = 0
    radar_counts, radar_region, lidar_region = [], [], []
    ranges, zs, rcs, vcomp = [], [], [], []
    azs, els, mags, vrs, lidar_fov = [], [], [], [], []
    has_rcs = has_v = has_mag = has_vr = True
    for frame in frames:
        n_frames += 1
        xyz = frame.radar.xyz.astype(np.float64)  # (N, 3) [x, y, z]
        radar_counts.append(len(xyz))
        radar_region.append(int(crop_mask(xyz, grid).sum()))
        lidar_region.append(int(crop_mask(frame.lidar.xyz, grid).sum()))
        r = np.linalg.norm(xyz, axis=1)
        ranges.append(r)
        zs.append(xyz[:, 2])
        azs.append(np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])))
        els.append(np.degrees(np.arcsin(np.clip(xyz[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0))))
        lx = frame.lidar.xyz.astype(np.float64)  # (M, 3)
        l_az = np.degrees(np.arctan2(lx[:, 1], lx[:, 0]))
        in_fov = (lx[:, 0] > 0) & (np.abs(l_az) <= FOV_AZ_DEG) & (np.hypot(lx[:, 0], lx[:, 1]) <= FOV_RANGE_M)
        lidar_fov.append(int(in_fov.sum()))
        has_rcs &= frame.radar.has("rcs")
        has_v &= frame.radar.has("v_r_compensated")
        has_mag &= frame.radar.has("mag")
        has_vr &= frame.radar.has("v_r")
        if has_rcs:
            rcs.append(frame.radar.column("rcs"))
        if has_v:
            vcomp.append(frame.radar.column("v_r_compensated"))
        if has_mag:
            mags.append(frame.radar.column("mag"))
        if has_vr:
            vrs.append(frame.radar.column("v_r"))
    if n_frames == 0:
        raise ValueError("compute_stats needs at least one frame")
    r = np.concatenate(ranges)
    z = np.concatenate(zs)

    def pct(values: np.ndarray, q: float) -> float:
        return float(np.percentile(values, q)) if len(values) else float("nan")

    rcs_all = np.concatenate(rcs) if has_rcs else None
    v_all = np.concatenate(vcomp) if has_v else None
    mag_all = np.concatenate(mags) if has_mag else None
    vr_all = np.concatenate(vrs) if has_vr else None
    az, el = np.concatenate(azs), np.concatenate(els)
    counts = np.asarray(radar_counts, dtype=np.float64)
    return RealismStats(
        frames=n_frames,
        radar_points=float(np.mean(radar_counts)),
        radar_in_region=float(np.mean(radar_region)),
        lidar_in_region=float(np.mean(lidar_region)),
        lidar_radar_ratio=float(sum(lidar_region) / max(sum(radar_region), 1)),
        range_median=pct(r, 50),
        range_p90=pct(r, 90),
        rcs_median=None if rcs_all is None else pct(rcs_all, 50),
        rcs_p10=None if rcs_all is None else pct(rcs_all, 10),
        rcs_p90=None if rcs_all is None else pct(rcs_all, 90),
        z_p5=pct(z, 5),
        z_p95=pct(z, 95),
        moving_share=None
        if v_all is None
        else float(np.mean(np.abs(v_all) > MOVING_SPEED))
        if len(v_all)
        else float("nan"),
        radar_points_p5=pct(counts, 5),
        radar_points_p95=pct(counts, 95),
        azimuth_p5=pct(az, 5),
        azimuth_p95=pct(az, 95),
        elevation_p5=pct(el, 5),
        elevation_p50=pct(el, 50),
        elevation_p95=pct(el, 95),
        mag_median=None if mag_all is None else pct(mag_all, 50),
        mag_p10=None if mag_all is None else pct(mag_all, 10),
        mag_p90=None if mag_all is None else pct(mag_all, 90),
        vr_p5=None if vr_all is None else pct(vr_all, 5),
        vr_p95=None if vr_all is None else pct(vr_all, 95),
        lidar_in_fov=float(np.mean(lidar_fov)),
    )


def format_stats(
    stats: RealismStats, targets: dict[str, tuple[float, float]] | None = None, label: str = "VoD"
) -> str:
    """A table: statistic, value, target band (``targets``, default VoD's, named ``label``), and a
    mark where the value is outside it."""
    bands = REALISM_TARGETS if targets is None else targets
    bad = set(stats.out_of_band(bands))
    lines = [f"{'statistic':<20} {'value':>12}  {label + ' target':>20}"]
    for f in fields(stats):
        value = getattr(stats, f.name)
        shown = "n/a" if value is None else f"{value:.0f}" if f.name == "frames" else f"{value:.3f}"
        band = bands.get(f.name)
        band_s = "" if band is None else f"{band[0]:g} .. {band[1]:g}"
        mark = "  << outside" if f.name in bad else ""
        lines.append(f"{f.name:<20} {shown:>12}  {band_s:>20}{mark}")
    return "\n".join(lines)
