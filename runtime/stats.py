"""Realism statistics of a radar + LiDAR dataset (DESIGN.md section 2), real or simulated.

Measured on raw frames (before preprocessing), in the radar frame. "Region" is the grid box of
``grid`` (default: the paper grid) intersected with ``|azimuth| <= grid.fov_deg``. LiDAR is
counted with its ground. Radar range, RCS, z and motion are pooled over all radar points of
all frames (not only the region). ``REALISM_TARGETS`` holds the bands DESIGN.md gives from the
three real VoD example frames; the "about" figures are read as the bands noted beside them.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, fields

import numpy as np

from msdnet.runtime.datasets.frame import Frame
from msdnet.runtime.grid import GRID_PRESETS, GridConfig
from msdnet.runtime.preprocess import crop_mask

MOVING_SPEED = 0.5  # m/s: |v_r_compensated| above this counts as moving

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
    has_rcs = has_v = True
    for frame in frames:
        n_frames += 1
        xyz = frame.radar.xyz.astype(np.float64)  # (N, 3) [x, y, z]
        radar_counts.append(len(xyz))
        radar_region.append(int(crop_mask(xyz, grid).sum()))
        lidar_region.append(int(crop_mask(frame.lidar.xyz, grid).sum()))
        ranges.append(np.linalg.norm(xyz, axis=1))
        zs.append(xyz[:, 2])
        has_rcs &= frame.radar.has("rcs")
        has_v &= frame.radar.has("v_r_compensated")
        if has_rcs:
            rcs.append(frame.radar.column("rcs"))
        if has_v:
            vcomp.append(frame.radar.column("v_r_compensated"))
    if n_frames == 0:
        raise ValueError("compute_stats needs at least one frame")
    r = np.concatenate(ranges)
    z = np.concatenate(zs)

    def pct(values: np.ndarray, q: float) -> float:
        return float(np.percentile(values, q)) if len(values) else float("nan")

    rcs_all = np.concatenate(rcs) if has_rcs else None
    v_all = np.concatenate(vcomp) if has_v else None
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
    )


def format_stats(stats: RealismStats, targets: dict[str, tuple[float, float]] | None = None) -> str:
    """A table: statistic, value, VoD target band, and a mark where the value is outside it."""
    bands = REALISM_TARGETS if targets is None else targets
    bad = set(stats.out_of_band(bands))
    lines = [f"{'statistic':<20} {'value':>12}  {'VoD target':>20}"]
    for f in fields(stats):
        value = getattr(stats, f.name)
        shown = "n/a" if value is None else f"{value:.0f}" if f.name == "frames" else f"{value:.3f}"
        band = bands.get(f.name)
        band_s = "" if band is None else f"{band[0]:g} .. {band[1]:g}"
        mark = "  << outside" if f.name in bad else ""
        lines.append(f"{f.name:<20} {shown:>12}  {band_s:>20}{mark}")
    return "\n".join(lines)
