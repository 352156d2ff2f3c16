"""Parts of the radar model beyond the direct returns: glints, multipath ghosts, clutter.

See the model description in :mod:`msdnet.runtime.sim.radar` (steps 2, 7 and 8); the functions
here are called from :class:`msdnet.runtime.sim.radar.RadarSim` and take its config.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from msdnet.runtime.sim import materials as mt
from msdnet.runtime.sim.radar_config import RadarConfig
from msdnet.runtime.sim.raycast import BOX, COS, CX, CY, KIND, MAT, SIN, Z1, A, B


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on a uint64 array (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        x = x ^ (x >> np.uint64(30))
        x = x * np.uint64(0xBF58476D1CE4E5B9)
        x = x ^ (x >> np.uint64(27))
        x = x * np.uint64(0x94D049BB133111EB)
        return x ^ (x >> np.uint64(31))


def _unit(h: np.ndarray) -> np.ndarray:
    """uint64 hashes (N,) -> uniform floats in [0, 1)."""
    return (h >> np.uint64(11)).astype(np.float64) / 2.0**53


def glint_rcs(
    p_hit: np.ndarray, mat: np.ndarray, area: np.ndarray, density: np.ndarray, cfg: RadarConfig
) -> np.ndarray:
    """Step 2, glints: each ray's share of the glint in the world-fixed cube it hits.

    p_hit: (N, 3) world hit points; mat: (N,) material ids; area: (N,) ray footprints (m^2);
    density: (N_MATERIALS,) share of cubes holding a glint. Returns (N,) RCS in m^2 (0 where
    the cube holds none). A cube's glint and its RCS come from a hash of the cube, so they
    stay put from scan to scan.
    """
    cell = np.floor(p_hit / mt.GLINT_CELL).astype(np.int64).astype(np.uint64)  # (N, 3) cube
    h = _mix(cell[:, 0] * np.uint64(0x9E3779B97F4A7C15) ^ _mix(cell[:, 1] ^ _mix(cell[:, 2])))
    h2 = _mix(h)
    v = _unit(h2) + 2.0**-54  # (0, 1)
    w = _unit(_mix(h2))
    z = np.sqrt(-2.0 * np.log(v)) * np.cos(2.0 * np.pi * w)  # standard normal (Box-Muller)
    rcs_db = cfg.glint_rcs_db + cfg.glint_spread_db * z
    share = np.minimum(area / mt.GLINT_CELL**2, 1.0)
    return np.where(_unit(h) < density[mat], 10.0 ** (rcs_db / 10.0) * share, 0.0)


def facade_faces(prims: np.ndarray, origin: np.ndarray, reach: float) -> np.ndarray:
    """Vertical faces of facade/glass boxes within ``reach`` m of ``origin`` (3,).

    Returns (F, 10) float64 rows [prim index, nx, ny, d, tx, ty, half length, centre x,
    centre y, top z]: outward normal n, plane n . p = d, tangent t.
    """
    is_wall = (prims[:, KIND] == BOX) & np.isin(prims[:, MAT], (mt.FACADE, mt.GLASS))
    dist = np.hypot(prims[:, CX] - origin[0], prims[:, CY] - origin[1])
    idx = np.flatnonzero(is_wall & (dist < reach + np.hypot(prims[:, A], prims[:, B])))
    p = prims[idx]
    c, s = p[:, COS], p[:, SIN]
    rows = []
    for sign in (1.0, -1.0):
        for along_x in (True, False):
            if along_x:  # the faces at local x = +-A, normal along the box's x axis
                n, t, off, half = np.stack([c, s], 1), np.stack([-s, c], 1), p[:, A], p[:, B]
            else:
                n, t, off, half = np.stack([-s, c], 1), np.stack([c, s], 1), p[:, B], p[:, A]
            n = sign * n
            centre = p[:, [CX, CY]] + n * off[:, None]  # (K, 2) face centre
            d = np.sum(n * centre, axis=1)
            rows.append(np.column_stack([idx, n, d, t, half, centre, p[:, Z1]]))
    return np.concatenate(rows)


def facade_ghosts(
    faces: np.ndarray,
    origin: np.ndarray,
    p_w: np.ndarray,
    v_w: np.ndarray,
    power: np.ndarray,
    cast: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    cfg: RadarConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 7a: mirror images of targets behind the facades that reflect them to the radar.

    faces: from :func:`facade_faces`; origin: (3,) radar position; p_w, v_w: (S, 3) target
    positions and velocities (world); power: (S,) target RCS without the antenna pattern;
    cast: unit world directions (G, 3) -> (hit distance (G,), primitive index (G,)).
    Returns ghost positions (G, 3), velocities (G, 3) and RCS before the pattern (G,).
    """
    empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    if len(p_w) == 0 or len(faces) == 0:
        return empty
    n = faces[:, 1:3]  # (F, 2)
    h_r = origin[:2] @ n.T - faces[:, 3]  # (F,) radar in front of each plane by
    h_p = p_w[:, :2] @ n.T - faces[None, :, 3]  # (S, F) target in front of each plane by
    mirror = p_w[:, None, :2] - 2.0 * h_p[..., None] * n[None]  # (S, F, 2) image xy
    s = h_r[None, :] / np.maximum(h_r[None, :] + h_p, 1e-9)  # (S, F) radar -> image fraction
    q_xy = origin[:2] + s[..., None] * (mirror - origin[:2])  # (S, F, 2) specular point
    q_z = origin[2] + s * (p_w[:, None, 2] - origin[2])  # (S, F)
    along = np.einsum("sfk,fk->sf", q_xy - faces[None, :, 7:9], faces[:, 4:6])
    valid = (
        (h_r[None, :] > 0.5)
        & (h_p > 0.3)
        & (np.abs(along) <= faces[None, :, 6])
        & (q_z >= 0.0)
        & (q_z <= faces[None, :, 9])
    )
    dist = np.where(valid, np.linalg.norm(mirror - origin[:2], axis=2), np.inf)  # (S, F)
    best = np.argmin(dist, axis=1)  # nearest image per target
    src = np.flatnonzero(np.isfinite(dist[np.arange(len(p_w)), best]))
    src = src[rng.random(len(src)) < cfg.ghost_prob]
    if len(src) == 0:
        return empty
    f = best[src]
    to_q = np.column_stack([q_xy[src, f], q_z[src, f]]) - origin  # (G, 3)
    dq = np.linalg.norm(to_q, axis=1)
    t, hit = cast(to_q / dq[:, None])
    seen = (hit == faces[f, 0].astype(np.int64)) & (np.abs(t - dq) < 0.3)  # Q is visible
    src, f = src[seen], f[seen]
    nrm = np.column_stack([faces[f, 1:3], np.zeros(len(f))])  # (G, 3)
    pos = np.column_stack([mirror[src, f], p_w[src, 2]])
    vel = v_w[src] - 2.0 * np.sum(v_w[src] * nrm, axis=1, keepdims=True) * nrm
    gain = 10.0 ** (cfg.facade_bounce_db / 10.0) * rng.exponential(size=len(src))
    return pos, vel, power[src] * gain


def ground_ghosts(
    p_w: np.ndarray, v_w: np.ndarray, power: np.ndarray, cfg: RadarConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 7b: mirror images below the road (z -> -z) of targets above it; same layout as
    :func:`facade_ghosts`."""
    pick = np.flatnonzero((p_w[:, 2] > 0.05) & (rng.random(len(p_w)) < cfg.ground_ghost_prob))
    pos = p_w[pick] * np.array([1.0, 1.0, -1.0])
    vel = v_w[pick] * np.array([1.0, 1.0, -1.0])
    gain = 10.0 ** (cfg.ground_bounce_db / 10.0) * rng.exponential(size=len(pick))
    return pos, vel, power[pick] * gain


def clutter(
    cfg: RadarConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 8: uniform false alarms: range (n,), azimuth (n,), elevation (n,) in rad, SNR (n,)
    linear, just around the detection threshold, and measured radial speed (n,) m/s."""
    n = int(rng.poisson(cfg.clutter_rate))
    r = rng.uniform(cfg.min_range, cfg.max_range, n)
    az = np.radians(rng.uniform(-cfg.az_fov_deg, cfg.az_fov_deg, n))
    el = np.radians(rng.uniform(-cfg.el_fov_deg, cfg.el_fov_deg, n))
    snr_half = np.log(cfg.pfa) / np.log(0.5) - 1.0  # SNR detected with probability 0.5
    snr = snr_half * rng.uniform(0.5, 2.0, n)
    v_r = rng.uniform(-cfg.max_doppler, cfg.max_doppler, n)
    return r, az, el, snr, v_r
