"""Numba ray caster over analytic primitives: yaw-oriented boxes, vertical cylinders, ellipsoids.

A scene is a table of primitives, one row each (float64 columns named below), plus the ground
plane z = 0 (asphalt). Boxes are oriented by yaw only and span ``[Z0, Z1]`` in height; cylinders
are vertical; ellipsoids have a horizontal radius ``A`` and span ``[Z0, Z1]``.

Acceleration: for every sensor position the primitives are binned by the azimuth interval their
bounding circle covers (``build_sectors``), each sector sorted by the nearest horizontal distance
of its primitives, so a ray tests only the primitives of its own sector and stops as soon as its
best hit is nearer than the next candidate.

Porous materials: a mesh surface (fence) lets a ray pass with a probability; a volumetric one
(tree crown) stops a ray after an exponential free path inside it (the ray passes when the path
is longer than the chord). Both draws come from a hash of (salt, ray, primitive), so they are
deterministic and independent of thread scheduling.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from msdnet.runtime.sim.materials import ASPHALT

# primitive kinds
BOX = 0
CYLINDER = 1
ELLIPSOID = 2

# primitive table columns
KIND = 0  # BOX, CYLINDER or ELLIPSOID
CX = 1  # m, centre x (world)
CY = 2  # m, centre y (world)
Z0 = 3  # m, bottom
Z1 = 4  # m, top
A = 5  # m, box half-length along its own x / cylinder or ellipsoid radius
B = 6  # m, box half-width along its own y (unused otherwise)
COS = 7  # cos(yaw) of a box
SIN = 8  # sin(yaw) of a box
MAT = 9  # material id (materials.py)
OBJ = 10  # object id (several primitives of one car share it), -1 for static scenery
VX = 11  # m/s, world velocity x (0 for static)
VY = 12  # m/s, world velocity y
N_COLS = 13

NO_HIT = -1  # primitive index of a ray that hit nothing
GROUND = -2  # primitive index of a ray that hit the ground plane


def hit_materials(prims: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Material id of each hit (N,) int64: the primitive's, asphalt for the ground.

    prims: (P, N_COLS); hit: (N,) primitive indices or GROUND (no NO_HIT expected).
    """
    mat = np.full(len(hit), ASPHALT, dtype=np.int64)
    obj = hit >= 0
    mat[obj] = prims[hit[obj], MAT].astype(np.int64)
    return mat


@njit(cache=True)
def _hash01(salt: np.uint64, a: np.int64, b: np.int64) -> float:
    """Uniform [0, 1) from (salt, a, b): splitmix64 finaliser."""
    x = salt ^ (np.uint64(a) * np.uint64(0x9E3779B97F4A7C15)) ^ (np.uint64(b + 7) << np.uint64(32))
    x ^= x >> np.uint64(30)
    x *= np.uint64(0xBF58476D1CE4E5B9)
    x ^= x >> np.uint64(27)
    x *= np.uint64(0x94D049BB133111EB)
    x ^= x >> np.uint64(31)
    return float(x >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True)
def _bound_radius(p: np.ndarray) -> float:
    """Horizontal bounding-circle radius of one primitive row."""
    if p[KIND] == BOX:
        return np.sqrt(p[A] * p[A] + p[B] * p[B])
    return p[A]


@njit(cache=True)
def build_sectors(
    prims: np.ndarray, origin: np.ndarray, n_sectors: int, max_range: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bin primitives by the world azimuths they cover as seen from ``origin``.

    prims: (P, N_COLS) float64; origin: (3,) float64 [x, y, z] world.
    Returns ``start`` (n_sectors + 1,) int64 offsets into ``items`` (K,) int64 primitive
    indices, and ``near`` (K,) float64 nearest horizontal distance of each listed primitive;
    within a sector, items are sorted by ``near``.
    """
    n = prims.shape[0]
    lo = np.empty(n, np.int64)
    hi = np.empty(n, np.int64)
    dnear = np.empty(n, np.float64)
    width = 2.0 * np.pi / n_sectors
    counts = np.zeros(n_sectors, np.int64)
    for i in range(n):
        dx = prims[i, CX] - origin[0]
        dy = prims[i, CY] - origin[1]
        d = np.sqrt(dx * dx + dy * dy)
        rho = _bound_radius(prims[i])
        dnear[i] = max(d - rho, 0.0)
        if d - rho > max_range:
            lo[i] = 0
            hi[i] = -1
            continue
        if d <= rho * 1.0001:
            lo[i] = 0
            hi[i] = n_sectors - 1
        else:
            half = np.arcsin(rho / d)
            az = np.arctan2(dy, dx)
            lo[i] = np.int64(np.floor((az - half + np.pi) / width))
            hi[i] = np.int64(np.floor((az + half + np.pi) / width))
            if hi[i] - lo[i] >= n_sectors:
                lo[i] = 0
                hi[i] = n_sectors - 1
        for s in range(lo[i], hi[i] + 1):
            counts[s % n_sectors] += 1
    start = np.zeros(n_sectors + 1, np.int64)
    for s in range(n_sectors):
        start[s + 1] = start[s] + counts[s]
    items = np.empty(start[n_sectors], np.int64)
    fill = start[:-1].copy()
    for i in range(n):
        for s in range(lo[i], hi[i] + 1):
            k = s % n_sectors
            items[fill[k]] = i
            fill[k] += 1
    near = np.empty(start[n_sectors], np.float64)
    for s in range(n_sectors):
        seg = items[start[s] : start[s + 1]]
        order = np.argsort(dnear[seg], kind="mergesort")
        items[start[s] : start[s + 1]] = seg[order]
        for k in range(start[s], start[s + 1]):
            near[k] = dnear[items[k]]
    return start, items, near


@njit(cache=True)
def _hit_box(p, ox, oy, oz, dx, dy, dz):
    """Entry distance and outward normal (world) of a ray on a yaw box; t < 0 when missed."""
    c = p[COS]
    s = p[SIN]
    rx = ox - p[CX]
    ry = oy - p[CY]
    lox = c * rx + s * ry
    loy = -s * rx + c * ry
    ldx = c * dx + s * dy
    ldy = -s * dx + c * dy
    tmin = -1e30
    tmax = 1e30
    axis = -1
    sign = 0.0
    # slabs: local x, local y, z
    for k in range(3):
        if k == 0:
            o, d, lo, hi = lox, ldx, -p[A], p[A]
        elif k == 1:
            o, d, lo, hi = loy, ldy, -p[B], p[B]
        else:
            o, d, lo, hi = oz, dz, p[Z0], p[Z1]
        if abs(d) < 1e-12:
            if o < lo or o > hi:
                return -1.0, 0.0, 0.0, 0.0
            continue
        t1 = (lo - o) / d
        t2 = (hi - o) / d
        sg = -1.0
        if t1 > t2:
            t1, t2 = t2, t1
            sg = 1.0
        if t1 > tmin:
            tmin = t1
            axis = k
            sign = sg
        tmax = min(tmax, t2)
        if tmin > tmax:
            return -1.0, 0.0, 0.0, 0.0
    if tmin <= 0.0 or axis < 0:  # missed, or the origin is inside the box
        return -1.0, 0.0, 0.0, 0.0
    if axis == 0:
        return tmin, sign * c, sign * s, 0.0
    if axis == 1:
        return tmin, -sign * s, sign * c, 0.0
    return tmin, 0.0, 0.0, sign


@njit(cache=True)
def _hit_cylinder(p, ox, oy, oz, dx, dy, dz):
    """Entry distance and outward normal of a ray on a vertical cylinder; t < 0 when missed."""
    rx = ox - p[CX]
    ry = oy - p[CY]
    r = p[A]
    a = dx * dx + dy * dy
    best = -1.0
    nx = 0.0
    ny = 0.0
    nz = 0.0
    if a > 1e-12:
        b = rx * dx + ry * dy
        c = rx * rx + ry * ry - r * r
        disc = b * b - a * c
        if disc >= 0.0 and c > 0.0:
            t = (-b - np.sqrt(disc)) / a
            z = oz + t * dz
            if t > 0.0 and p[Z0] <= z <= p[Z1]:
                best = t
                nx = (rx + t * dx) / r
                ny = (ry + t * dy) / r
    if abs(dz) > 1e-12:
        cap = p[Z1] if dz < 0.0 else p[Z0]
        inside = (oz > p[Z1]) if dz < 0.0 else (oz < p[Z0])
        t = (cap - oz) / dz
        if inside and t > 0.0 and (best < 0.0 or t < best):
            qx = rx + t * dx
            qy = ry + t * dy
            if qx * qx + qy * qy <= r * r:
                best = t
                nx = 0.0
                ny = 0.0
                nz = 1.0 if dz < 0.0 else -1.0
    return best, nx, ny, nz


@njit(cache=True)
def _hit_ellipsoid(p, ox, oy, oz, dx, dy, dz):
    """Entry and exit distances and entry normal on an ellipsoid; t < 0 when missed."""
    r = p[A]
    rz = 0.5 * (p[Z1] - p[Z0])
    cz = 0.5 * (p[Z1] + p[Z0])
    qx = (ox - p[CX]) / r
    qy = (oy - p[CY]) / r
    qz = (oz - cz) / rz
    ex = dx / r
    ey = dy / r
    ez = dz / rz
    a = ex * ex + ey * ey + ez * ez
    b = qx * ex + qy * ey + qz * ez
    c = qx * qx + qy * qy + qz * qz - 1.0
    disc = b * b - a * c
    if disc < 0.0 or c <= 0.0:
        return -1.0, -1.0, 0.0, 0.0, 0.0
    sq = np.sqrt(disc)
    t0 = (-b - sq) / a
    t1 = (-b + sq) / a
    if t0 <= 0.0:
        return -1.0, -1.0, 0.0, 0.0, 0.0
    nx = (qx + t0 * ex) / r
    ny = (qy + t0 * ey) / r
    nz = (qz + t0 * ez) / rz
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    return t0, t1, nx / nn, ny / nn, nz / nn


@njit(cache=True)
def cast_rays(
    prims: np.ndarray,
    origin: np.ndarray,
    rot: np.ndarray,
    dirs: np.ndarray,
    max_range: float,
    start: np.ndarray,
    items: np.ndarray,
    near: np.ndarray,
    mesh_pass: np.ndarray,
    free_path: np.ndarray,
    salt: np.uint64,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast rays from one origin; first hit per ray.

    prims: (P, N_COLS); origin: (3,) world; rot: (3, 3) sensor-to-world rotation;
    dirs: (R, 3) unit directions in the sensor frame (rotated by ``rot`` here);
    start / items / near: from :func:`build_sectors` for this origin;
    mesh_pass, free_path: (N_MATERIALS,) per-material pass probability and free path (m).
    Returns ``t`` (R,) float64 hit distance (inf when none), ``hit`` (R,) int64 primitive index
    (NO_HIT, GROUND or >= 0), ``cos_inc`` (R,) float64 |cos| of the incidence angle.
    """
    n_rays = dirs.shape[0]
    n_sectors = start.shape[0] - 1
    width = 2.0 * np.pi / n_sectors
    t_out = np.full(n_rays, np.inf)
    hit_out = np.full(n_rays, NO_HIT, np.int64)
    cos_out = np.zeros(n_rays)
    ox, oy, oz = origin[0], origin[1], origin[2]
    for r in range(n_rays):
        sx, sy, sz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        dx = rot[0, 0] * sx + rot[0, 1] * sy + rot[0, 2] * sz
        dy = rot[1, 0] * sx + rot[1, 1] * sy + rot[1, 2] * sz
        dz = rot[2, 0] * sx + rot[2, 1] * sy + rot[2, 2] * sz
        horiz = np.sqrt(dx * dx + dy * dy)
        best = max_range
        best_i = NO_HIT
        best_cos = 0.0
        if dz < -1e-9:
            tg = -oz / dz
            if tg < best:
                best = tg
                best_i = GROUND
                best_cos = -dz
        sec = np.int64(np.floor((np.arctan2(dy, dx) + np.pi) / width))
        sec = min(max(sec, 0), n_sectors - 1)
        for k in range(start[sec], start[sec + 1]):
            if best * horiz < near[k]:
                break
            i = items[k]
            p = prims[i]
            kind = p[KIND]
            mat = np.int64(p[MAT])
            if kind == BOX:
                t, nx, ny, nz = _hit_box(p, ox, oy, oz, dx, dy, dz)
            elif kind == CYLINDER:
                t, nx, ny, nz = _hit_cylinder(p, ox, oy, oz, dx, dy, dz)
            else:
                t, t_exit, nx, ny, nz = _hit_ellipsoid(p, ox, oy, oz, dx, dy, dz)
                if t > 0.0 and free_path[mat] > 0.0:
                    u = _hash01(salt, r, i)
                    depth = -np.log(1.0 - u) * free_path[mat]
                    if t + depth > t_exit:
                        continue
                    t = t + depth
                    nx, ny, nz = -dx, -dy, -dz  # inside foliage the "surface" faces the ray
            if t <= 0.0 or t >= best:
                continue
            if mesh_pass[mat] > 0.0 and _hash01(salt, r, i + 1000003) < mesh_pass[mat]:
                continue
            best = t
            best_i = i
            best_cos = abs(nx * dx + ny * dy + nz * dz)
        if best_i != NO_HIT:
            t_out[r] = best
            hit_out[r] = best_i
            cos_out[r] = best_cos
    return t_out, hit_out, cos_out
