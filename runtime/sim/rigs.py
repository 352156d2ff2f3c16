"""The simulated vehicles: ``vod`` (VoD-like, the default) and ``astyx`` (Astyx HiRes2019-like).

A rig is its sensor mountings (:mod:`msdnet.runtime.sim.rig`), its LiDAR and radar models and
the speeds it drives at. ``vod``: HDL-64-like LiDAR, ZF FRGen21-like radar (a few hundred
points), 4-9 m/s. ``astyx``: VLP-16 LiDAR, an Astyx 6455-like radar (about two thousand points
per scan, finer cells, a wider elevation spread), 5-14 m/s; numbers measured on the real frames
in docs/sim-astyx-rig.md.

Astyx radar columns. The Astyx 6455 reports ``x y z v_r mag``: ``mag`` is a received magnitude
in dB, quantised to 0.5 dB, starting at its detection floor of 45 and nearly flat in range (it is
an SNR-like power, not an RCS); ``v_r`` is the measured radial speed, positive for an
approaching target, folded into +-``VR_FOLD`` m/s (static points read ``wrap(+v_ego . u)``).
The Astyx rig keeps the VoD 7-column ``.bin`` rows so the VoD reader reads it, with:

    column 3 (``rcs`` in the VoD layout)  mag = MAG_FLOOR + MAG_SCALE (10 log10(SNR) - MAG_SNR0_DB),
                                          quantised to MAG_STEP, at least MAG_FLOOR
    column 4 (``v_r``)                    Astyx v_r = fold(-v_r_sim, VR_FOLD) (sign flipped)
    column 5 (``v_r_compensated``)        the simulator's ego-compensated v_r (VoD sign), kept
    column 6 (``time``)                   0

``--dataset sim-astyx`` (``runtime/io/datasets/sim_astyx.py``) reads such a folder with the Astyx
names, radar columns ``x y z v_r mag`` (as ``--dataset astyx``), so a model pretrained on it is
fine-tuned on Astyx with the same inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msdnet.runtime.sim import rig as mount
from msdnet.runtime.sim.lidar import VLP16, LidarConfig
from msdnet.runtime.sim.radar import RadarConfig, RadarSim

MAG_FLOOR = 45.0  # dB, the Astyx 6455's smallest reported magnitude
MAG_STEP = 0.5  # dB, quantisation of the reported magnitude
MAG_SCALE = 0.7  # dB of mag per dB of SNR (the real magnitudes spread less than the sim's SNR)
MAG_SNR0_DB = 14.0  # dB, SNR reported at the floor; with MAG_SCALE, lands the mag median on Astyx's
VR_FOLD = 5.3  # m/s, |v_r| folds beyond this (fit on the real frames: 4.6-5.5 m/s)

# Astyx 6455-like radar: finer cells and a narrower peak search than VoD's (many more points),
# a stronger link budget; tuned against the real frames (docs/sim-astyx-rig.md).
ASTYX_RADAR = RadarConfig(
    az_fov_deg=60.0,
    el_fov_deg=15.0,
    range_res=0.15,
    az_res_deg=0.8,
    el_res_deg=2.0,
    ray_az_step_deg=0.2,
    ray_el_step_deg=0.5,
    snr_db_at_100m=30.0,  # a stronger link budget: detections out to 100 m
    near_floor_range=90.0,  # SNR falls as 1/r^2 up to 90 m: fewer near points, more far ones
    az_pattern_db=8.0,
    el_pattern_db=55.0,  # with beam_el_deg: elevation 5th-95th percentile about -6 .. +8 deg
    beam_el_deg=0.0,
    peak_window=(0, 1, 0),  # no peak search over elevation: ~2,000 points per scan
    cfar_factor_db=6.5,
    el_noise_floor_deg=0.8,
    ground_ghost_prob=0.6,  # more points below the road (Astyx z 5th percentile -2.8 m)
    clutter_rate=40.0,  # false alarms per scan
    max_doppler=VR_FOLD,  # clutter Doppler within the folded interval
)


@dataclass(frozen=True)
class SimRig:
    """One simulated vehicle: mountings, sensor models, driving speeds, radar column mapping."""

    name: str  # "vod" or "astyx" (msdnet-data simulate --rig)
    mounting: mount.Rig  # where the sensors sit (rig.py)
    lidar: LidarConfig  # LiDAR model
    radar: RadarConfig  # radar model
    cruise_speed: tuple[float, float]  # m/s, uniform range of a sequence's cruise speed
    astyx_columns: bool  # radar rows carry Astyx-like mag / v_r in columns 3 / 4 (see above)


SIM_RIGS: dict[str, SimRig] = {
    "vod": SimRig("vod", mount.VOD, LidarConfig(), RadarConfig(), (4.0, 9.0), False),
    "astyx": SimRig("astyx", mount.ASTYX, VLP16, ASTYX_RADAR, (5.0, 14.0), True),
}


def fold(v: np.ndarray, limit: float) -> np.ndarray:
    """Radial speeds (N,) folded into [-limit, limit) (Doppler ambiguity)."""
    return (v + limit) % (2.0 * limit) - limit


def astyx_rows(points: np.ndarray, radar: RadarSim) -> np.ndarray:
    """VoD-layout radar rows (N, 7) [x, y, z, rcs, v_r, v_r_compensated, time] -> the same rows
    with Astyx-like values: column 3 the magnitude, column 4 the Astyx v_r (module docstring).

    The SNR is the radar equation of ``radar`` on the reported RCS at the point's range."""
    out = points.copy()
    r = np.linalg.norm(points[:, :3].astype(np.float64), axis=1)
    snr = radar.snr(10.0 ** (points[:, 3].astype(np.float64) / 10.0), r)
    mag = MAG_FLOOR + MAG_SCALE * (10.0 * np.log10(np.maximum(snr, 1e-12)) - MAG_SNR0_DB)
    out[:, 3] = np.maximum(np.round(mag / MAG_STEP) * MAG_STEP, MAG_FLOOR)
    out[:, 4] = fold(-points[:, 4].astype(np.float64), VR_FOLD)
    return out
