"""Procedural street scenes around an ego route, as a table of analytic primitives.

Layout per city block (the rectangle between four streets): a raised island (sidewalk and kerb,
concrete) and, along each of its four sides, a row of buildings (facade boxes of random length,
depth and height) with gaps; a gap holds a fence, a hedge or nothing (an alley). On the
sidewalks: lamp posts and sign posts, street trees (trunk cylinder + crown ellipsoid), parked
bicycles; in the parking lane: parked cars (metal body + glass cabin). Moving objects (cars in
the oncoming lane, cyclists on the cycle track, pedestrians on the sidewalk) are placed so the
ego meets them during the sequence; they move at constant velocity.

All rows follow the column layout of :mod:`msdnet.runtime.sim.raycast`; materials are ids of
:mod:`msdnet.runtime.sim.materials`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msdnet.runtime.sim import materials as mt
from msdnet.runtime.sim.raycast import BOX, CX, CY, CYLINDER, ELLIPSOID, N_COLS, VX, VY
from msdnet.runtime.sim.trajectory import LANE_OFFSET, StreetGrid, Trajectory

SCENE_RADIUS = 140.0  # m, blocks farther than this from every route sample are not built


@dataclass(frozen=True)
class Scene:
    """Primitives of one sequence at t = 0; moving rows carry their velocity."""

    prims: np.ndarray  # (P, N_COLS) float64, raycast column layout
    n_moving: int  # number of moving objects (cars, cyclists, pedestrians)

    def at(self, t: float) -> np.ndarray:
        """Primitives at time ``t`` s: moving rows advanced by velocity * t. (P, N_COLS)."""
        p = self.prims.copy()
        p[:, CX] += p[:, VX] * t
        p[:, CY] += p[:, VY] * t
        return p


class _Rows:
    """Accumulates primitive rows and hands out object ids."""

    def __init__(self) -> None:
        self.rows: list[list[float]] = []
        self.next_obj = 0

    def obj(self) -> int:
        self.next_obj += 1
        return self.next_obj - 1

    def box(self, c, z0, z1, hx, hy, yaw, mat, obj=-1, vel=(0.0, 0.0)) -> None:
        cs, sn = np.cos(yaw), np.sin(yaw)
        self.rows.append([BOX, c[0], c[1], z0, z1, hx, hy, cs, sn, mat, obj, vel[0], vel[1]])

    def cyl(self, c, z0, z1, r, mat, obj=-1, vel=(0.0, 0.0)) -> None:
        self.rows.append([CYLINDER, c[0], c[1], z0, z1, r, 0, 1, 0, mat, obj, vel[0], vel[1]])

    def ell(self, c, z0, z1, r, mat, obj=-1, vel=(0.0, 0.0)) -> None:
        self.rows.append([ELLIPSOID, c[0], c[1], z0, z1, r, 0, 1, 0, mat, obj, vel[0], vel[1]])

    def car(self, c, yaw, obj=-1, vel=(0.0, 0.0), base=0.0, rng=None) -> None:
        """Body (metal) + cabin (glass); 4.4 x 1.8 x 1.5 m."""
        length = 4.4 if rng is None else float(rng.uniform(3.8, 4.9))
        self.box(c, base + 0.25, base + 1.0, length / 2, 0.9, yaw, mt.METAL, obj, vel)
        self.box(c, base + 1.0, base + 1.5, length / 4 + 0.1, 0.8, yaw, mt.GLASS, obj, vel)

    def pedestrian(self, c, base, obj=-1, vel=(0.0, 0.0)) -> None:
        self.cyl(c, base, base + 1.5, 0.2, mt.HUMAN, obj, vel)
        self.ell(c, base + 1.5, base + 1.75, 0.11, mt.HUMAN, obj, vel)

    def cyclist(self, c, yaw, base, obj=-1, vel=(0.0, 0.0)) -> None:
        self.box(c, base + 0.05, base + 1.0, 0.85, 0.06, yaw, mt.FENCE, obj, vel)  # bicycle
        self.cyl(c, base + 0.9, base + 1.55, 0.22, mt.HUMAN, obj, vel)
        self.ell(c, base + 1.55, base + 1.8, 0.11, mt.HUMAN, obj, vel)

    def table(self) -> np.ndarray:
        return np.array(self.rows, dtype=np.float64).reshape(-1, N_COLS)  # (P, N_COLS)


def _near_route(lo: np.ndarray, hi: np.ndarray, route_xy: np.ndarray, radius: float) -> bool:
    """Whether the rectangle [lo, hi] (2,) is within ``radius`` of any route sample (K, 2)."""
    d = np.maximum(np.maximum(lo - route_xy, route_xy - hi), 0.0)  # (K, 2) gap per axis
    return bool(np.min(np.hypot(d[:, 0], d[:, 1])) <= radius)


def _block_side(
    rows: _Rows, rng, corner, t, n, length: float, width: float, grid: StreetGrid, kerb: float
) -> None:
    """Buildings, gaps and street furniture along one side of a block.

    corner: (2,) kerb corner where the side starts; t: (2,) unit direction along the side;
    n: (2,) unit normal into the block; length, width: block size along t and n, m.
    """
    yaw = float(np.arctan2(t[1], t[0]))
    setback = float(rng.uniform(0.0, 1.5))
    line = grid.sidewalk + setback  # building line, from the kerb
    end = length - line  # buildings stay behind the cross streets' building lines
    u = line
    while end - u > 3.0:
        if rng.random() < 0.25:  # gap
            gap = float(min(rng.uniform(4.0, 14.0), end - u))
            mid = corner + t * (u + gap / 2) + n * line
            kind = rng.random()
            if kind < 0.4:
                h = float(rng.uniform(1.2, 2.0))
                rows.box(mid, kerb, kerb + h, gap / 2, 0.03, yaw, mt.FENCE)
            elif kind < 0.7:
                h = float(rng.uniform(0.9, 1.8))
                rows.box(mid + n * 0.4, kerb, kerb + h, gap / 2, 0.4, yaw, mt.VEGETATION)
            u += gap
            continue
        blen = float(min(rng.uniform(8.0, 30.0), end - u))
        depth = float(min(rng.uniform(8.0, 18.0), width - 2.0 * line))
        height = float(rng.uniform(4.0, 12.0) if rng.random() < 0.9 else rng.uniform(12.0, 18.0))
        mat = mt.GLASS if rng.random() < 0.08 else mt.FACADE
        centre = corner + t * (u + blen / 2) + n * (line + depth / 2)
        rows.box(centre, 0.0, height, blen / 2, depth / 2, yaw, mat)
        u += blen
    # lamp posts and sign posts, near the kerb
    u = float(rng.uniform(2.0, 20.0))
    while u < length - 1.0:
        p = corner + t * u + n * 0.35
        if rng.random() < 0.7:
            rows.cyl(p, kerb, kerb + float(rng.uniform(5.0, 8.0)), float(rng.uniform(0.06, 0.1)), mt.METAL)
        else:
            top = kerb + float(rng.uniform(2.2, 2.8))
            rows.cyl(p, kerb, top, 0.04, mt.METAL)
            rows.box(p - n * 0.03, top - 0.6, top, 0.3, 0.015, yaw, mt.SIGN)
        u += float(rng.uniform(15.0, 35.0))
    if rng.random() < 0.7:  # tree-lined side
        u = float(rng.uniform(2.0, 10.0))
        while u < length - 2.0:
            p = corner + t * u + n * float(rng.uniform(0.8, 1.4))
            trunk = float(rng.uniform(2.0, 3.5))
            rows.cyl(p, kerb, kerb + trunk, float(rng.uniform(0.12, 0.3)), mt.WOOD)
            r = float(rng.uniform(1.5, 3.2))
            rz = float(rng.uniform(1.5, 3.0))
            rows.ell(p, kerb + trunk - 0.5, kerb + trunk - 0.5 + 2 * rz, r, mt.VEGETATION)
            u += float(rng.uniform(7.0, 13.0))
    if rng.random() < 0.5:  # a cluster of parked bicycles, perpendicular to the kerb
        u = float(rng.uniform(3.0, max(length - 8.0, 3.5)))
        for k in range(int(rng.integers(3, 11))):
            p = corner + t * (u + 0.6 * k) + n * float(rng.uniform(1.0, 1.6))
            rows.box(p, kerb + 0.05, kerb + 1.0, 0.85, 0.05, yaw + np.pi / 2, mt.FENCE, rows.obj())
    # parked cars along the kerb, on streets wide enough that the parking lane (inner edge
    # road_half - 1.85) clears the ego lane (outer edge LANE_OFFSET * road_half + 0.9)
    if grid.road_half >= 5.4 and rng.random() < 0.6:
        u = float(rng.uniform(6.0, 10.0))
        while u < length - 6.0:
            if rng.random() < 0.75:
                flip = np.pi if rng.random() < 0.2 else 0.0
                rows.car(corner + t * u - n * 0.95, yaw + flip, rows.obj(), rng=rng)
            u += float(rng.uniform(5.2, 7.5))


def _blocks(rows: _Rows, rng, grid: StreetGrid, route_xy: np.ndarray) -> None:
    """All blocks near the route: island, then the four sides."""
    rh = grid.road_half
    for i in range(len(grid.xs) - 1):
        for j in range(len(grid.ys) - 1):
            lo = np.array([grid.xs[i] + rh, grid.ys[j] + rh])
            hi = np.array([grid.xs[i + 1] - rh, grid.ys[j + 1] - rh])
            if not _near_route(lo, hi, route_xy, SCENE_RADIUS):
                continue
            # one generator per block, so a block looks the same whatever the route
            brng = np.random.default_rng([int(rng.integers(2**31)), i, j])
            kerb = float(brng.uniform(0.11, 0.16))
            size = hi - lo
            rows.box((lo + hi) / 2, 0.0, kerb, size[0] / 2, size[1] / 2, 0.0, mt.CONCRETE)
            sides = [  # (corner, along, inward normal, axis along): S, E, N, W counter-clockwise
                (lo, np.array([1.0, 0.0]), np.array([0.0, 1.0]), 0),
                (np.array([hi[0], lo[1]]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), 1),
                (hi, np.array([-1.0, 0.0]), np.array([0.0, -1.0]), 0),
                (np.array([lo[0], hi[1]]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), 1),
            ]
            for corner, t, n, axis in sides:
                length, width = float(size[axis]), float(size[1 - axis])
                _block_side(rows, brng, corner, t, n, length, width, grid, kerb)


def _movers(rows: _Rows, rng, grid: StreetGrid, traj: Trajectory, busy: float) -> int:
    """Moving cars, cyclists and pedestrians the ego meets; returns how many."""
    duration = max(float(traj.time[-1]), 1.0)
    lane = LANE_OFFSET * grid.road_half
    n_total = 0
    counts = {
        "car": rng.poisson(busy * (3.0 + 1.0 * duration)),
        "cyclist": rng.poisson(busy * (8.0 + 2.0 * duration)),
        "pedestrian": rng.poisson(busy * (5.0 + 1.0 * duration)),
    }
    for kind, count in counts.items():
        for _ in range(int(count)):
            f = int(rng.integers(len(traj.xy)))  # frame at which the ego meets it
            ahead = float(rng.uniform(0.0, 40.0))
            d_ego = np.array([np.cos(traj.yaw[f]), np.sin(traj.yaw[f])])
            k = int(np.argmin(np.linalg.norm(traj.route_xy - (traj.xy[f] + ahead * d_ego), axis=1)))
            p, d = traj.route_xy[k], traj.route_dir[k]
            if np.min(np.abs(d)) > 0.01:  # in a turn: streets run along the axes, skip it
                continue
            right = np.array([d[1], -d[0]])
            if kind == "car":
                pos = p - 2 * lane * right  # oncoming lane
                heading = -d
                speed = float(rng.uniform(4.0, 12.0))
                base = 0.0
            elif kind == "cyclist":
                side = 1.0 if rng.random() < 0.6 else -1.0
                pos = p + (side * (grid.road_half + 0.9) - lane) * right  # cycle track
                heading = d if rng.random() < 0.6 else -d
                speed = float(rng.uniform(2.5, 6.0))
                base = 0.13
            else:
                side = 1.0 if rng.random() < 0.5 else -1.0
                off = grid.road_half + grid.sidewalk * float(rng.uniform(0.4, 0.8))
                pos = p + (side * off - lane) * right  # sidewalk
                heading = d if rng.random() < 0.5 else -d
                speed = float(rng.uniform(0.8, 1.8))
                base = 0.13
            vel = heading * speed
            p0 = pos - vel * traj.time[f]  # where it is at t = 0
            yaw = float(np.arctan2(heading[1], heading[0]))
            obj = rows.obj()
            if kind == "car":
                rows.car(p0, yaw, obj, (vel[0], vel[1]), rng=rng)
            elif kind == "cyclist":
                rows.cyclist(p0, yaw, base, obj, (vel[0], vel[1]))
            else:
                rows.pedestrian(p0, base, obj, (vel[0], vel[1]))
            n_total += 1
    return n_total


def build_scene(
    rng: np.random.Generator, grid: StreetGrid, traj: Trajectory, moving: bool, busy: float
) -> Scene:
    """The scene of one sequence: blocks near the route, plus movers when ``moving``."""
    rows = _Rows()
    _blocks(rows, rng, grid, traj.route_xy)
    n_moving = _movers(rows, rng, grid, traj, busy) if moving else 0
    return Scene(rows.table(), n_moving)
