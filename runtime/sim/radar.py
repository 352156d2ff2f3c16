"""4D radar model: what a single automotive radar scan (VoD's ZF FRGen21-like) returns.

The project learns to turn these points into LiDAR-like clouds, so the model aims at the
statistics of real VoD scans (few hundred points, noisy elevation, ghosts, clutter) rather than
at wave physics. One scan, step by step:

1. Sampling the scene. Rays are cast from the radar over its field of view (azimuth +-60 deg,
   elevation +-15 deg) on a grid several times finer than the radar's resolution
   (``ray_az_step_deg`` x ``ray_el_step_deg``, shifted by a random sub-step every scan). Each
   ray stops at its first surface; foliage lets rays in by an exponential free path and fences
   let some through (``materials.py``). Hits outside 0.5-100 m are dropped.
2. Backscatter per ray. A ray stands for the patch it covers, of area ``A = r^2 dAz dEl / cos i``
   (i: incidence angle). Its radar cross-section is
   ``sigma = r^2 dAz dEl * (s_d cos i + s_s exp(-(i / w)^2))`` with the material's diffuse
   coefficient ``s_d`` (Lambert, cos^2 i per unit area), its specular coefficient ``s_s`` and
   lobe width ``w``. Per unit area: metal >> facade > glass > concrete > vegetation > human >
   asphalt, so a car side facing the radar is far brighter than a wall, a wall than a tree.
3. Resolution cells. Rays fall into range x azimuth x elevation cells of ``range_res`` (0.2 m)
   x ``az_res_deg`` (1.5 deg) x ``el_res_deg`` (3 deg). A cell's power is the sum of its rays'
   sigma; its position, material and velocity are those of its strongest ray. Speckle: the
   power is multiplied by an exponential draw (Swerling I).
4. CFAR and peak picking (what keeps extended surfaces sparse): a cell is a candidate only
   when its power is the largest of its neighbourhood (``peak_window`` cells each side in
   range, azimuth, elevation: the elevation window is wide, since a 4D radar estimates few
   elevations per range-azimuth-Doppler peak) and exceeds
   ``cfar_factor_db`` times the mean of ``cfar_train`` range cells on each side (beyond
   ``cfar_guard`` guard cells) plus the noise floor (cell-averaging CFAR along range).
5. Detection. ``SNR = sigma * 10^(snr_db_at_1m / 10) / r^4`` (radar equation). A candidate is
   detected with the Swerling I probability ``Pd = Pfa^(1 / (1 + SNR))``.
6. Measurement noise. Range +- ``range_noise``; azimuth and elevation errors are Gaussian with
   ``sigma = floor + res / sqrt(2 SNR)`` (Cramer-Rao-like), and the elevation floor is several
   times the azimuth one (sparse vertical aperture): elevation is the noisiest coordinate.
   The reported RCS is the cell power in dBsm plus ``rcs_noise_db`` Gaussian noise.
7. Multipath ghosts. (a) Facades: for every detection stronger than ``ghost_min_rcs_db`` and
   every facade face (building box side) that both the radar and the target are in front of,
   the specular point Q on the face along the radar -> mirror-image line is found; when Q lies
   on the face and the radar sees Q, the target's mirror image behind the facade becomes a
   ghost, with the target's power times ``facade_bounce_db`` (two bounces) and the mirrored
   velocity; kept with probability ``ghost_prob`` and the detection test at the ghost's range.
   (b) Ground: the road mirrors targets below the ground plane (``ground_bounce_db``,
   ``ground_ghost_prob``) - points below the road, as real scans show.
8. Clutter. Poisson(``clutter_rate``) false alarms uniform in range, azimuth and elevation,
   with an RCS just above the detection threshold at their range and a random Doppler.
9. Doppler. ``v_r = (v_target - v_radar) . u`` with u the unit line of sight (positive when
   receding), plus ``vr_noise``; ``v_r_compensated = v_r + v_radar_est . u`` where the ego
   velocity estimate carries a small odometry error, so static points read ~0 and movers their
   own radial speed. ``time`` is 0 (a single scan; accumulated clouds use -1, -2, ...).

Output rows are in the radar frame: float32 ``x y z rcs v_r v_r_compensated time``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msdnet.runtime.sim import materials as mt
from msdnet.runtime.sim.raycast import (
    BOX,
    CX,
    CY,
    GROUND,
    KIND,
    MAT,
    VX,
    VY,
    A,
    B,
    COS,
    SIN,
    Z1,
    build_sectors,
    cast_rays,
)


FACADE_GHOST = -1  # source label of a multipath ghost behind a facade
GROUND_GHOST = -2  # source label of a ghost mirrored below the road
CLUTTER = -3  # source label of a uniform false alarm


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
    snr_db_at_100m: float = 30.0  # SNR in dB of a 1 m^2 target at 100 m on boresight
    near_floor_range: float = 50.0  # m, nearer than this the detection floor rises as 1/r^2
    az_pattern_db: float = 12.0  # two-way antenna gain lost at the azimuth FoV edge (quadratic)
    el_pattern_db: float = 12.0  # two-way antenna gain lost at the elevation FoV edge
    pfa: float = 1e-3  # false-alarm probability setting the Swerling I detection curve
    peak_window: tuple[int, int, int] = (1, 1, 2)  # peak half-widths in (range, az, el) cells
    cfar_guard: int = 1  # CA-CFAR guard cells each side in range
    cfar_train: int = 4  # CA-CFAR training cells each side in range
    cfar_factor_db: float = 8.0  # CA-CFAR threshold over the training mean (plus noise)
    range_noise: float = 0.05  # m, 1-sigma
    az_noise_floor_deg: float = 0.3  # degrees, 1-sigma azimuth error at high SNR
    el_noise_floor_deg: float = 1.5  # degrees, 1-sigma elevation error at high SNR
    rcs_noise_db: float = 1.0  # dB, 1-sigma error of the reported RCS
    vr_noise: float = 0.05  # m/s, 1-sigma radial-velocity error
    ego_speed_noise: float = 0.05  # m/s, 1-sigma error of the ego velocity used to compensate
    ghost_min_rcs_db: float = -5.0  # dBsm, weakest detection that makes multipath ghosts
    facade_bounce_db: float = -9.0  # dB, power kept after facade -> target -> facade
    ghost_prob: float = 0.6  # probability a geometric facade ghost is produced
    ground_bounce_db: float = -6.0  # dB, power kept by a ground-bounce ghost
    ground_ghost_prob: float = 0.15  # probability of a ground ghost per strong detection
    clutter_rate: float = 25.0  # mean uniform false alarms per scan
    max_doppler: float = 15.0  # m/s, unambiguous radial speed (clutter Doppler is uniform in it)
    n_sectors: int = 720  # azimuth bins of the ray caster's acceleration structure


def _sph_to_xyz(r: np.ndarray, az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """Range (N,) m, azimuth and elevation (N,) rad -> (N, 3) [x, y, z]."""
    ce = np.cos(el)
    return np.stack([r * ce * np.cos(az), r * ce * np.sin(az), r * np.sin(el)], axis=1)


def _facade_faces(prims: np.ndarray, origin: np.ndarray, reach: float) -> np.ndarray:
    """Vertical faces of facade/glass boxes within ``reach`` m: (F, 9) float64 rows
    [prim index, nx, ny, d, tx, ty, half length, centre x, centre y] with outward normal n,
    plane n . p = d, tangent t."""
    is_wall = (prims[:, KIND] == BOX) & np.isin(prims[:, MAT], (mt.FACADE, mt.GLASS))
    dist = np.hypot(prims[:, CX] - origin[0], prims[:, CY] - origin[1])
    idx = np.flatnonzero(is_wall & (dist < reach + np.hypot(prims[:, A], prims[:, B])))
    rows = []
    for sign in (1.0, -1.0):
        for along_x in (True, False):
            p = prims[idx]
            c, s = p[:, COS], p[:, SIN]
            if along_x:  # faces at local x = +-A, normal along the box x axis
                n = sign * np.stack([c, s], axis=1)
                t = np.stack([-s, c], axis=1)
                off, half = p[:, A], p[:, B]
            else:
                n = sign * np.stack([-s, c], axis=1)
                t = np.stack([c, s], axis=1)
                off, half = p[:, B], p[:, A]
            centre = p[:, [CX, CY]] + n * off[:, None]  # (K, 2) face centre
            d = np.sum(n * centre, axis=1)
            rows.append(np.column_stack([idx, n, d, t, half, centre]))
    return np.concatenate(rows) if rows else np.zeros((0, 9))


def _detect(snr: np.ndarray, pfa: float, rng: np.random.Generator) -> np.ndarray:
    """Swerling I detection draw: True with probability pfa^(1 / (1 + SNR)). snr: (N,) linear."""
    return rng.random(len(snr)) < np.power(pfa, 1.0 / (1.0 + snr))


class _Sampler:
    """The radar's sampling rays for one scan, in the radar frame (see step 1)."""

    def __init__(self, cfg: RadarConfig, rng: np.random.Generator) -> None:
        n_az = int(round(2 * cfg.az_fov_deg / cfg.ray_az_step_deg))
        n_el = int(round(2 * cfg.el_fov_deg / cfg.ray_el_step_deg))
        az = -cfg.az_fov_deg + (np.arange(n_az) + rng.random()) * cfg.ray_az_step_deg  # (n_az,)
        el = -cfg.el_fov_deg + (np.arange(n_el) + rng.random()) * cfg.ray_el_step_deg  # (n_el,)
        grid_az, grid_el = np.meshgrid(np.radians(az), np.radians(el), indexing="ij")
        self.az = grid_az.ravel()  # (R,) rad
        self.el = grid_el.ravel()  # (R,) rad
        self.dirs = _sph_to_xyz(np.ones_like(self.az), self.az, self.el)  # (R, 3) radar frame
        self.d_omega = np.radians(cfg.ray_az_step_deg) * np.radians(cfg.ray_el_step_deg)


class RadarSim:
    """Runs the radar model on one scene snapshot (see the module docstring for the model)."""

    def __init__(self, cfg: RadarConfig) -> None:
        self.cfg = cfg
        self.diffuse = 10.0 ** (mt.material_array("radar_diffuse_db") / 10.0)
        self.specular = 10.0 ** (mt.material_array("radar_specular_db") / 10.0)
        self.lobe = np.radians(mt.material_array("radar_lobe_deg"))
        self.mesh_pass = mt.material_array("radar_pass")
        self.free_path = mt.material_array("radar_free_path")
        self.n_r = int(np.ceil(cfg.max_range / cfg.range_res)) + 1
        self.n_a = int(np.ceil(2 * cfg.az_fov_deg / cfg.az_res_deg))
        self.n_e = int(np.ceil(2 * cfg.el_fov_deg / cfg.el_res_deg))

    def _cast(self, prims, origin, dirs_world, salt):
        start, items, near = build_sectors(prims, origin, self.cfg.n_sectors, self.cfg.max_range)
        return cast_rays(
            prims,
            origin,
            np.ascontiguousarray(dirs_world),
            self.cfg.max_range,
            start,
            items,
            near,
            self.mesh_pass,
            self.free_path,
            np.uint64(salt),
        )

    def _snr(self, power: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Step 5: linear SNR of apparent RCS ``power`` (m^2) at range ``r`` (m), both (N,)."""
        cfg = self.cfg
        r = np.maximum(r, cfg.min_range)
        floor = np.maximum(1.0, (cfg.near_floor_range / r) ** 2)
        return power * 10.0 ** (cfg.snr_db_at_100m / 10.0) * (100.0 / r) ** 4 / floor

    def _pattern(self, az: np.ndarray, el: np.ndarray) -> np.ndarray:
        """Two-way antenna gain (linear, 1 on boresight) at azimuth / elevation (rad): (N,)."""
        cfg = self.cfg
        loss_db = cfg.az_pattern_db * (np.degrees(az) / cfg.az_fov_deg) ** 2
        loss_db += cfg.el_pattern_db * (np.degrees(el) / cfg.el_fov_deg) ** 2
        return 10.0 ** (-loss_db / 10.0)

    def _cells(self, t, az, el, sigma, rng):
        """Steps 3-4: strongest ray per cell, speckled cell power, peak flag.
        Returns (ray index of each cell (K,), cell power (K,), is_peak (K,))."""
        cfg = self.cfg
        ir = np.minimum((t / cfg.range_res).astype(np.int64), self.n_r - 1)
        ia = np.clip(((np.degrees(az) + cfg.az_fov_deg) / cfg.az_res_deg).astype(np.int64), 0, self.n_a - 1)
        ie = np.clip(((np.degrees(el) + cfg.el_fov_deg) / cfg.el_res_deg).astype(np.int64), 0, self.n_e - 1)
        key = (ir * self.n_a + ia) * self.n_e + ie  # (N,) flat cell index
        order = np.lexsort((-sigma, key))
        key_sorted = key[order]
        first = np.r_[True, key_sorted[1:] != key_sorted[:-1]]
        strongest = order[first]  # (K,) ray index of each occupied cell
        cell_key = key_sorted[first]  # (K,)
        total = np.bincount(key, weights=sigma, minlength=self.n_r * self.n_a * self.n_e)
        power = total[cell_key] * rng.exponential(size=len(cell_key))  # Swerling I speckle
        kr = cell_key // (self.n_a * self.n_e)
        ka = (cell_key // self.n_e) % self.n_a
        ke = cell_key % self.n_e
        g, n_train = cfg.cfar_guard, cfg.cfar_train
        wr, wa, we = cfg.peak_window
        pad = max(g + n_train + 1, wr)
        # (range, az, el) cube of cell powers, zero-padded on every side
        cube = np.zeros((self.n_r + 2 * pad, self.n_a + 2 * wa, self.n_e + 2 * we))
        i, a, e = kr + pad, ka + wa, ke + we
        cube[i, a, e] = power
        neigh = np.zeros_like(power)
        for dr in range(-wr, wr + 1):
            for da in range(-wa, wa + 1):
                for de in range(-we, we + 1):
                    if dr or da or de:
                        neigh = np.maximum(neigh, cube[i + dr, a + da, e + de])
        # CA-CFAR along range: mean of n_train cells each side beyond g guard cells
        csum = np.cumsum(cube, axis=0)  # csum[i] = sum of cube[: i + 1]
        lead = csum[i - g - 1, a, e] - csum[i - g - n_train - 1, a, e]
        lag = csum[i + g + n_train, a, e] - csum[i + g, a, e]
        train = (lead + lag) / (2 * n_train)
        noise = 1.0 / self._snr(np.ones(len(kr)), (kr + 0.5) * cfg.range_res)
        cfar = power > 10.0 ** (cfg.cfar_factor_db / 10.0) * (train + noise)
        return strongest, power, (power >= neigh) & cfar

    def _measure(self, r, az, el, power, snr, rng):
        """Step 6: noisy range, angles and RCS. Returns (N, 3) radar-frame xyz and (N,) RCS."""
        cfg = self.cfg
        root = np.sqrt(2.0 * np.maximum(snr, 1e-3))
        s_az = np.radians(cfg.az_noise_floor_deg + cfg.az_res_deg / root)
        s_el = np.radians(cfg.el_noise_floor_deg + cfg.el_res_deg / root)
        r_m = np.maximum(r + rng.normal(0.0, cfg.range_noise, len(r)), cfg.min_range)
        az_m = az + rng.normal(0.0, 1.0, len(r)) * s_az
        el_m = el + rng.normal(0.0, 1.0, len(r)) * s_el
        rcs = 10.0 * np.log10(np.maximum(power, 1e-12)) + rng.normal(0.0, cfg.rcs_noise_db, len(r))
        return _sph_to_xyz(r_m, az_m, el_m), rcs

    def scan(
        self,
        prims: np.ndarray,
        radar_to_world: np.ndarray,
        v_radar: np.ndarray,
        rng: np.random.Generator,
        salt: int,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One scan. prims: (P, N_COLS) scene at this time; radar_to_world: (4, 4);
        v_radar: (3,) world velocity of the radar, m/s.

        Returns points (N, 7) float32 [x, y, z, rcs, v_r, v_r_compensated, time] in the radar
        frame, and source (N,) int8: the material id of a real detection, or FACADE_GHOST,
        GROUND_GHOST, CLUTTER (negative)."""
        cfg = self.cfg
        rot, origin = radar_to_world[:3, :3], radar_to_world[:3, 3].copy()
        smp = _Sampler(cfg, rng)
        dirs_w = smp.dirs @ rot.T  # (R, 3) world
        t, hit, cos_i = self._cast(prims, origin, dirs_w, salt)
        keep = np.flatnonzero(np.isfinite(t) & (t >= cfg.min_range))
        t, hit, cos_i = t[keep], hit[keep], np.clip(cos_i[keep], 0.0, 1.0)
        mat = np.where(hit == GROUND, mt.ASPHALT, prims[np.maximum(hit, 0), MAT]).astype(np.int64)
        inc = np.arccos(cos_i)
        sigma = t**2 * smp.d_omega * (
            self.diffuse[mat] * cos_i + self.specular[mat] * np.exp(-((inc / self.lobe[mat]) ** 2))
        )  # (N,) m^2 per ray
        az, el = smp.az[keep], smp.el[keep]
        sigma *= self._pattern(az, el)  # apparent RCS: the radar does not undo its pattern
        ray, power, peak = self._cells(t, az, el, sigma, rng)
        snr = self._snr(power, t[ray])
        det = peak & _detect(snr, cfg.pfa, rng)
        ray, power, snr = ray[det], power[det], snr[det]
        # true geometry of the detections (world) and their targets' velocity
        u_w = dirs_w[keep[ray]]  # (D, 3) line of sight
        p_w = origin + u_w * t[ray, None]  # (D, 3)
        h = hit[ray]
        v_obj = np.zeros((len(ray), 3))
        v_obj[h >= 0, 0] = prims[h[h >= 0], VX]
        v_obj[h >= 0, 1] = prims[h[h >= 0], VY]
        parts = [(t[ray], az[ray], el[ray], power, snr, u_w, v_obj)]
        sources = [mat[ray]]
        strong = 10.0 * np.log10(np.maximum(power, 1e-12)) > cfg.ghost_min_rcs_db
        true_power = power[strong] / self._pattern(az[ray[strong]], el[ray[strong]])
        ghosts = self._facade_ghosts(prims, origin, p_w[strong], v_obj[strong], true_power, salt, rng)
        ghosts += self._ground_ghosts(p_w[strong], v_obj[strong], true_power, origin, rng)
        for g_pos, g_vel, g_pow, g_src in ghosts:
            rel = g_pos - origin
            r_g = np.linalg.norm(rel, axis=1)
            u_g = rel / np.maximum(r_g[:, None], 1e-9)
            loc = u_g @ rot  # (G, 3) line of sight in the radar frame
            az_g = np.arctan2(loc[:, 1], loc[:, 0])
            el_g = np.arcsin(np.clip(loc[:, 2], -1.0, 1.0))
            g_pow = g_pow * self._pattern(az_g, el_g)
            snr_g = self._snr(g_pow, r_g)
            ok = (
                (r_g <= cfg.max_range)
                & (np.abs(np.degrees(az_g)) <= cfg.az_fov_deg)
                & (np.abs(np.degrees(el_g)) <= cfg.el_fov_deg)
                & _detect(snr_g, cfg.pfa, rng)
            )
            parts.append((r_g[ok], az_g[ok], el_g[ok], g_pow[ok], snr_g[ok], u_g[ok], g_vel[ok]))
            sources.append(np.full(int(ok.sum()), g_src))
        parts.append(self._clutter(rot, rng))
        sources.append(np.full(len(parts[-1][0]), CLUTTER))
        r_all, az_all, el_all, pow_all, snr_all, u_all, v_all = (
            np.concatenate([p[k] for p in parts]) for k in range(7)
        )
        xyz, rcs = self._measure(r_all, az_all, el_all, pow_all, snr_all, rng)
        v_r = np.sum((v_all - v_radar) * u_all, axis=1) + rng.normal(0.0, cfg.vr_noise, len(r_all))
        v_est = v_radar + np.r_[rng.normal(0.0, cfg.ego_speed_noise, 2), 0.0]
        v_rc = v_r + u_all @ v_est
        out = np.zeros((len(r_all), 7), dtype=np.float32)
        out[:, :3] = xyz
        out[:, 3] = rcs
        out[:, 4] = v_r
        out[:, 5] = v_rc
        return out, np.concatenate(sources).astype(np.int8)

    def _facade_ghosts(self, prims, origin, p_w, v_w, power, salt, rng):
        """Step 7a: mirror images of strong detections behind facades the radar sees."""
        cfg = self.cfg
        faces = _facade_faces(prims, origin, cfg.max_range / 2)
        if len(p_w) == 0 or len(faces) == 0:
            return []
        n = faces[None, :, 1:3]  # (1, F, 2)
        n_r = origin[:2] @ faces[:, 1:3].T - faces[:, 3]  # (F,) radar's height above each plane
        # (S, F) target's height above each plane
        n_p = np.einsum("sk,fk->sf", p_w[:, :2], faces[:, 1:3]) - faces[None, :, 3]
        mirror = p_w[:, None, :2] - 2.0 * n_p[..., None] * n  # (S, F, 2) image xy
        s = n_r[None, :] / np.maximum(n_r[None, :] + n_p, 1e-9)  # (S, F) fraction to Q
        q_xy = origin[:2] + s[..., None] * (mirror - origin[:2])  # (S, F, 2)
        q_z = origin[2] + s * (p_w[:, None, 2] - origin[2])  # (S, F)
        along = np.einsum("sfk,fk->sf", q_xy - faces[None, :, 7:9], faces[:, 4:6])
        height = prims[faces[:, 0].astype(np.int64), Z1]
        valid = (
            (n_r[None, :] > 0.5)
            & (n_p > 0.3)
            & (np.abs(along) <= faces[None, :, 6])
            & (q_z >= 0.0)
            & (q_z <= height[None, :])
        )
        dist = np.where(valid, np.linalg.norm(mirror - origin[:2], axis=2), np.inf)  # (S, F)
        best = np.argmin(dist, axis=1)
        src = np.flatnonzero(np.isfinite(dist[np.arange(len(p_w)), best]))
        src = src[rng.random(len(src)) < cfg.ghost_prob]
        if len(src) == 0:
            return []
        f = best[src]
        q = np.column_stack([q_xy[src, f], q_z[src, f]])  # (G, 3) specular points
        to_q = q - origin
        dq = np.linalg.norm(to_q, axis=1)
        t, hit, _ = self._cast(prims, origin, to_q / dq[:, None], salt + 1)
        seen = (hit == faces[f, 0].astype(np.int64)) & (np.abs(t - dq) < 0.3)
        src, f = src[seen], f[seen]
        nrm = np.column_stack([faces[f, 1:3], np.zeros(len(f))])  # (G, 3)
        pos = np.column_stack([mirror[src, f], p_w[src, 2]])
        vel = v_w[src] - 2.0 * np.sum(v_w[src] * nrm, axis=1, keepdims=True) * nrm
        gain = 10.0 ** (cfg.facade_bounce_db / 10.0) * rng.exponential(size=len(src))
        return [(pos, vel, power[src] * gain, FACADE_GHOST)]

    def _ground_ghosts(self, p_w, v_w, power, origin, rng):
        """Step 7b: mirror images below the road of strong detections above it."""
        cfg = self.cfg
        pick = np.flatnonzero((p_w[:, 2] > 0.05) & (rng.random(len(p_w)) < cfg.ground_ghost_prob))
        pos = p_w[pick] * np.array([1.0, 1.0, -1.0])
        gain = 10.0 ** (cfg.ground_bounce_db / 10.0) * rng.exponential(size=len(pick))
        return [(pos, v_w[pick], power[pick] * gain, GROUND_GHOST)]

    def _clutter(self, rot, rng):
        """Step 8: uniform false alarms, returned in the layout of ``parts``."""
        cfg = self.cfg
        n = int(rng.poisson(cfg.clutter_rate))
        r = rng.uniform(cfg.min_range, cfg.max_range, n)
        az = np.radians(rng.uniform(-cfg.az_fov_deg, cfg.az_fov_deg, n))
        el = np.radians(rng.uniform(-cfg.el_fov_deg, cfg.el_fov_deg, n))
        snr_threshold = np.log(cfg.pfa) / np.log(0.5) - 1.0  # SNR at Pd = 0.5
        snr = snr_threshold * rng.uniform(0.5, 2.0, n)
        power = snr / self._snr(np.ones(n), r)
        u = _sph_to_xyz(np.ones(n), az, el) @ rot.T  # (n, 3) world line of sight
        v_r = rng.uniform(-cfg.max_doppler, cfg.max_doppler, n)
        # a velocity along the line of sight whose radial component is v_r relative to the radar
        return r, az, el, power, snr, u, u * v_r[:, None]
