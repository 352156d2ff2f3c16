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
   lobe width ``w`` (effective values in ``materials.py``, tuned so the statistics match VoD).
   Per unit area: metal >> facade > vegetation > human >> asphalt at grazing incidence, so a
   car side facing the radar is far brighter than a wall, a wall than a tree.
   Glints: real surfaces carry point scatterers (window frames, drain pipes, balconies, wheel
   arches). The world is cut into fixed ``GLINT_CELL`` cubes; a cube on a surface holds a
   glint with the material's ``radar_glint_density`` (a hash of the cube, so glints stay put
   from scan to scan) of RCS ``glint_rcs_db`` +- ``glint_spread_db`` times cos i (corner
   reflectors have broad but finite lobes); each ray hitting the cube carries its share
   ``A / GLINT_CELL^2`` of it.
3. Resolution cells. Rays fall into range x azimuth x elevation cells of ``range_res`` (0.2 m)
   x ``az_res_deg`` (1.5 deg) x ``el_res_deg`` (3 deg). A cell's power is the sum of its rays'
   sigma; its position, material and velocity are those of its strongest ray. Speckle: the
   power is multiplied by an exponential draw (Swerling I).
4. CFAR and peak picking (what keeps extended surfaces sparse). As a radar finds peaks over
   angle within each range(-Doppler) bin, a cell is a candidate only when its power is the
   largest of its neighbourhood of ``peak_window`` cells each side in (range, azimuth,
   elevation) - by default the same range cell, +-1 azimuth and +-2 elevation cells, so a
   facade yields a few points per range cell, not a wall of them - and exceeds
   ``cfar_factor_db`` times the mean of ``cfar_train`` range cells on each side (beyond
   ``cfar_guard`` guard cells) plus the noise floor (cell-averaging CFAR along range).
5. Detection. ``SNR = sigma G * 10^(snr_db_at_100m / 10) * (100 m / r)^4 / F(r)``: the radar
   equation (RCS over r^4) with G the two-way antenna gain (quadratic in dB: ``az_pattern_db``
   lost at the azimuth FoV edge, ``el_pattern_db`` 15 degrees off a beam centre tilted to
   ``beam_el_deg``, which keeps the road near the car visible and high facades far away faint;
   the reported RCS is sigma G, as a radar that does not undo its pattern) and
   F(r) = max(1, (``near_floor_range`` / r)^2) a noise floor that rises at short range
   (leakage, near clutter). A candidate is detected with the Swerling I probability
   ``Pd = Pfa^(1 / (1 + SNR))``.
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
   with an SNR around the detection threshold and a uniformly random measured Doppler.
9. Doppler. ``v_r = (v_target - v_radar) . u`` with u the unit line of sight (positive when
   receding), plus ``vr_noise``; ``v_r_compensated = v_r + v_radar_est . u`` where the ego
   velocity estimate carries a small odometry error, so static points read ~0 and movers their
   own radial speed. ``time`` is 0 (a single scan; accumulated clouds use -1, -2, ...).

Output rows are in the radar frame: float32 ``x y z rcs v_r v_r_compensated time``. The
defaults of :class:`RadarConfig` and the material table were tuned so that simulated folders
land in the VoD bands of ``msdnet.runtime.io.datasets.stats.REALISM_TARGETS`` (checked in tests/test_sim.py).
"""

from __future__ import annotations

import numpy as np

from msdnet.runtime.sim import materials as mt
from msdnet.runtime.sim import radar_effects as fx
from msdnet.runtime.sim.radar_config import RadarConfig
from msdnet.runtime.sim.raycast import VX, VY, build_sectors, cast_rays, hit_materials

FACADE_GHOST = -1  # source label of a multipath ghost behind a facade
GROUND_GHOST = -2  # source label of a ghost mirrored below the road
CLUTTER = -3  # source label of a uniform false alarm


def _sph_to_xyz(r: np.ndarray, az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """Range (N,) m, azimuth and elevation (N,) rad -> (N, 3) [x, y, z]."""
    ce = np.cos(el)
    return np.stack([r * ce * np.cos(az), r * ce * np.sin(az), r * np.sin(el)], axis=1)


def _detect(snr: np.ndarray, pfa: float, rng: np.random.Generator) -> np.ndarray:
    """Swerling I detection draw: True with probability pfa^(1 / (1 + SNR)). snr: (N,) linear."""
    return rng.random(len(snr)) < np.power(pfa, 1.0 / (1.0 + snr))


class RadarSim:
    """Runs the radar model on one scene snapshot (see the module docstring for the model)."""

    def __init__(self, cfg: RadarConfig | None = None) -> None:
        self.cfg = cfg = cfg or RadarConfig()
        self.diffuse = 10.0 ** (mt.material_array("radar_diffuse_db") / 10.0)
        self.specular = 10.0 ** (mt.material_array("radar_specular_db") / 10.0)
        self.lobe = np.radians(mt.material_array("radar_lobe_deg"))
        self.mesh_pass = mt.material_array("radar_pass")
        self.free_path = mt.material_array("radar_free_path")
        self.glint_density = mt.material_array("radar_glint_density")
        self.n_r = int(np.ceil(cfg.max_range / cfg.range_res)) + 1  # range cells
        self.n_a = int(np.ceil(2 * cfg.az_fov_deg / cfg.az_res_deg))  # azimuth cells
        self.n_e = int(np.ceil(2 * cfg.el_fov_deg / cfg.el_res_deg))  # elevation cells

    def _cast(self, prims, origin, dirs_world, salt):
        """First hits of world-frame rays (R, 3) from ``origin``: (t, hit, cos_i), each (R,)."""
        start, items, near = build_sectors(prims, origin, self.cfg.n_sectors, self.cfg.max_range)
        return cast_rays(
            prims,
            origin,
            np.eye(3),
            np.ascontiguousarray(dirs_world),
            self.cfg.max_range,
            start,
            items,
            near,
            self.mesh_pass,
            self.free_path,
            np.uint64(salt),
        )

    def snr(self, power: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Step 5: linear SNR of apparent RCS ``power`` (m^2) at range ``r`` (m), both (N,)."""
        cfg = self.cfg
        r = np.maximum(r, cfg.min_range)
        floor = np.maximum(1.0, (cfg.near_floor_range / r) ** 2)
        return power * 10.0 ** (cfg.snr_db_at_100m / 10.0) * (100.0 / r) ** 4 / floor

    def pattern(self, az: np.ndarray, el: np.ndarray) -> np.ndarray:
        """Two-way antenna gain (linear, 1 on boresight) at azimuth / elevation (rad): (N,)."""
        cfg = self.cfg
        loss_db = cfg.az_pattern_db * (np.degrees(az) / cfg.az_fov_deg) ** 2
        loss_db += cfg.el_pattern_db * ((np.degrees(el) - cfg.beam_el_deg) / cfg.el_fov_deg) ** 2
        return 10.0 ** (-loss_db / 10.0)

    def _cells(self, t, az, el, sigma, rng):
        """Steps 3-4 for rays at range t, azimuth az, elevation el (rad), RCS sigma, all (N,).
        Returns (ray index of each candidate (K,), speckled cell power (K,))."""
        cfg = self.cfg
        ir = np.minimum((t / cfg.range_res).astype(np.int64), self.n_r - 1)
        ia = ((np.degrees(az) + cfg.az_fov_deg) / cfg.az_res_deg).astype(np.int64)
        ie = ((np.degrees(el) + cfg.el_fov_deg) / cfg.el_res_deg).astype(np.int64)
        ia = np.clip(ia, 0, self.n_a - 1)
        ie = np.clip(ie, 0, self.n_e - 1)
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
        noise = 1.0 / self.snr(np.ones(len(kr)), (kr + 0.5) * cfg.range_res)
        cfar = power > 10.0 ** (cfg.cfar_factor_db / 10.0) * (train + noise)
        keep = (power >= neigh) & cfar
        return strongest[keep], power[keep]

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

    def _direct(self, prims, origin, rot, rng, salt):
        """Steps 1-5: detections as (r, az, el, power, snr, world hit (D, 3), target velocity
        (D, 3), material (D,))."""
        cfg = self.cfg
        n_az = int(round(2 * cfg.az_fov_deg / cfg.ray_az_step_deg))
        n_el = int(round(2 * cfg.el_fov_deg / cfg.ray_el_step_deg))
        az0 = -cfg.az_fov_deg + (np.arange(n_az) + rng.random()) * cfg.ray_az_step_deg
        el0 = -cfg.el_fov_deg + (np.arange(n_el) + rng.random()) * cfg.ray_el_step_deg
        grid_az, grid_el = np.meshgrid(np.radians(az0), np.radians(el0), indexing="ij")
        az, el = grid_az.ravel(), grid_el.ravel()  # (R,) rad, sampling rays
        dirs_w = _sph_to_xyz(np.ones_like(az), az, el) @ rot.T  # (R, 3) world
        t, hit, cos_i = self._cast(prims, origin, dirs_w, salt)
        keep = np.flatnonzero(np.isfinite(t) & (t >= cfg.min_range))
        t, hit, cos_i = t[keep], hit[keep], np.clip(cos_i[keep], 0.0, 1.0)
        az, el, dirs_w = az[keep], el[keep], dirs_w[keep]
        mat = hit_materials(prims, hit)
        d_omega = np.radians(cfg.ray_az_step_deg) * np.radians(cfg.ray_el_step_deg)
        lobe = np.exp(-((np.arccos(cos_i) / self.lobe[mat]) ** 2))
        sigma = t**2 * d_omega * (self.diffuse[mat] * cos_i + self.specular[mat] * lobe)
        area = t**2 * d_omega / np.maximum(cos_i, 0.05)  # (N,) m^2 ray footprints
        p_hit = origin + dirs_w * t[:, None]  # (N, 3) world hit points
        sigma += cos_i * fx.glint_rcs(p_hit, mat, area, self.glint_density, cfg)
        sigma *= self.pattern(az, el)  # apparent RCS
        ray, power = self._cells(t, az, el, sigma, rng)
        snr = self.snr(power, t[ray])
        det = _detect(snr, cfg.pfa, rng)
        ray, power, snr = ray[det], power[det], snr[det]
        h = hit[ray]
        vel = np.zeros((len(ray), 3))
        vel[h >= 0, 0] = prims[h[h >= 0], VX]
        vel[h >= 0, 1] = prims[h[h >= 0], VY]
        return t[ray], az[ray], el[ray], power, snr, p_hit[ray], vel, mat[ray]

    def scan(
        self,
        prims: np.ndarray,
        radar_to_world: np.ndarray,
        v_radar: np.ndarray,
        rng: np.random.Generator,
        salt: int,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One scan. prims: (P, N_COLS) scene at this time; radar_to_world: (4, 4);
        v_radar: (3,) world velocity of the radar, m/s; salt: seeds the ray caster's hashes.

        Returns points (N, 7) float32 [x, y, z, rcs, v_r, v_r_compensated, time] in the radar
        frame, and source (N,) int8: the material id of a real detection, or FACADE_GHOST,
        GROUND_GHOST, CLUTTER (negative)."""
        cfg = self.cfg
        rot, origin = radar_to_world[:3, :3], np.ascontiguousarray(radar_to_world[:3, 3])
        r, az, el, power, snr, p_w, vel, mat = self._direct(prims, origin, rot, rng, salt)
        u_w = (p_w - origin) / r[:, None]  # (D, 3) world line of sight
        parts = [(r, az, el, power, snr, u_w, vel, mat.astype(np.int8))]
        strong = 10.0 * np.log10(np.maximum(power, 1e-12)) > cfg.ghost_min_rcs_db
        bare = power[strong] / self.pattern(az[strong], el[strong])  # RCS without the pattern

        def cast(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            t, hit, _ = self._cast(prims, origin, dirs, salt + 1)
            return t, hit

        faces = fx.facade_faces(prims, origin, cfg.ghost_reach)
        ghosts = [
            (fx.facade_ghosts(faces, origin, p_w[strong], vel[strong], bare, cast, cfg, rng), FACADE_GHOST),
            (fx.ground_ghosts(p_w[strong], vel[strong], bare, cfg, rng), GROUND_GHOST),
        ]
        for (g_pos, g_vel, g_pow), label in ghosts:
            rel = g_pos - origin
            r_g = np.maximum(np.linalg.norm(rel, axis=1), 1e-6)
            u_g = rel / r_g[:, None]  # (G, 3) world line of sight
            loc = u_g @ rot  # (G, 3) line of sight in the radar frame
            az_g = np.arctan2(loc[:, 1], loc[:, 0])
            el_g = np.arcsin(np.clip(loc[:, 2], -1.0, 1.0))
            g_pow = g_pow * self.pattern(az_g, el_g)
            snr_g = self.snr(g_pow, r_g)
            ok = (
                (r_g <= cfg.max_range)
                & (np.abs(np.degrees(az_g)) <= cfg.az_fov_deg)
                & (np.abs(np.degrees(el_g)) <= cfg.el_fov_deg)
                & _detect(snr_g, cfg.pfa, rng)
            )
            src = np.full(int(ok.sum()), label, np.int8)
            parts.append((r_g[ok], az_g[ok], el_g[ok], g_pow[ok], snr_g[ok], u_g[ok], g_vel[ok], src))
        r_c, az_c, el_c, snr_c, vr_c = fx.clutter(cfg, rng)
        u_c = _sph_to_xyz(np.ones_like(r_c), az_c, el_c) @ rot.T  # (n, 3) world line of sight
        pow_c = snr_c / self.snr(np.ones_like(r_c), r_c)
        vel_c = v_radar + u_c * vr_c[:, None]  # a velocity whose measured v_r is vr_c
        parts.append((r_c, az_c, el_c, pow_c, snr_c, u_c, vel_c, np.full(len(r_c), CLUTTER, np.int8)))
        r, az, el, power, snr, u_w, vel, source = (np.concatenate([p[k] for p in parts]) for k in range(8))
        xyz, rcs = self._measure(r, az, el, power, snr, rng)
        v_r = np.sum((vel - v_radar) * u_w, axis=1) + rng.normal(0.0, cfg.vr_noise, len(r))
        v_est = v_radar + np.r_[rng.normal(0.0, cfg.ego_speed_noise, 2), 0.0]  # odometry
        out = np.zeros((len(r), 7), dtype=np.float32)  # time column stays 0: one scan
        out[:, :3] = xyz
        out[:, 3] = rcs
        out[:, 4] = v_r
        out[:, 5] = v_r + u_w @ v_est
        return out, source
