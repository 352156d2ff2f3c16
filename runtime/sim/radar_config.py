"""The simulated 4D radar's settings (runtime/sim/radar.py documents the model they drive), in a
module of their own so that the radar and its effects (radar_effects.py) both import them without
importing each other."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RadarConfig:
    """Radar field of view, resolution, detection and error model (see the module docstring)."""

    az_fov_deg: float = 60.0  # half field of view in azimuth, degrees
    el_fov_deg: float = 15.0  # half field of view in elevation, degrees
    min_range: float = 0.5  # m
    max_range: float = 100.0  # m
    range_res: float = 0.2  # m, range cell
    az_res_deg: float = 1.5  # degrees, azimuth cell
    el_res_deg: float = 3.0  # degrees, elevation cell
    ray_az_step_deg: float = 0.3  # degrees between sampling rays in azimuth
    ray_el_step_deg: float = 0.75  # degrees between sampling rays in elevation
    snr_db_at_100m: float = 16.5  # SNR in dB of a 1 m^2 target at 100 m on boresight
    near_floor_range: float = 40.0  # m, nearer than this the detection floor rises as 1/r^2
    az_pattern_db: float = 20.0  # two-way antenna gain lost at the azimuth FoV edge (quadratic)
    el_pattern_db: float = 50.0  # two-way gain lost 15 degrees off the beam's elevation centre
    beam_el_deg: float = -2.5  # elevation of the antenna beam's centre (negative: tilted down)
    pfa: float = 1e-3  # false-alarm probability setting the Swerling I detection curve
    glint_rcs_db: float = -0.5  # dBsm, median RCS of a glint (point scatterer on a surface)
    glint_spread_db: float = 10.0  # dB, 1-sigma spread of glint RCS around the median
    peak_window: tuple[int, int, int] = (0, 1, 2)  # peak half-widths in (range, az, el) cells
    cfar_guard: int = 1  # CA-CFAR guard cells each side in range
    cfar_train: int = 4  # CA-CFAR training cells each side in range
    cfar_factor_db: float = 8.0  # CA-CFAR threshold over the training mean (plus noise)
    range_noise: float = 0.05  # m, 1-sigma
    az_noise_floor_deg: float = 0.3  # degrees, 1-sigma azimuth error at high SNR
    el_noise_floor_deg: float = 1.5  # degrees, 1-sigma elevation error at high SNR
    rcs_noise_db: float = 1.0  # dB, 1-sigma error of the reported RCS
    vr_noise: float = 0.05  # m/s, 1-sigma radial-velocity error
    ego_speed_noise: float = 0.05  # m/s, 1-sigma error of the ego velocity used to compensate
    ghost_min_rcs_db: float = -10.0  # dBsm, weakest detection that makes multipath ghosts
    facade_bounce_db: float = -9.0  # dB, power kept after facade -> target -> facade
    ghost_prob: float = 0.6  # probability a geometric facade ghost is produced
    ghost_reach: float = 50.0  # m, facades farther than this make no ghosts
    ground_bounce_db: float = -6.0  # dB, power kept by a ground-bounce ghost
    ground_ghost_prob: float = 0.3  # probability of a ground ghost per strong detection
    clutter_rate: float = 8.0  # mean uniform false alarms per scan
    max_doppler: float = 15.0  # m/s, unambiguous radial speed (clutter Doppler is uniform in it)
    n_sectors: int = 720  # azimuth bins of the ray caster's acceleration structure
