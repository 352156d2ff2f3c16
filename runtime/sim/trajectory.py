"""Street grid and ego trajectories: routes through intersections, turns, stops, loops, at 10 Hz.

World frame: metres, x east, y north, z up, ground at z = 0. Streets run along the lines of a
rectangular grid with random block lengths. A route is a list of intersections; the ego drives
in the right-hand lane, corners are circular fillets, and the speed profile respects a cruise
speed, a lateral-acceleration limit in turns, acceleration/braking limits and optional stops
before intersections. A loop route circles one block once (four turns the same way) and then
drives on, so it passes its start again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FRAME_DT = 0.1  # s, 10 Hz frames
LANE_OFFSET = 0.45  # lane centre from the street centre line, as a fraction of road_half


@dataclass(frozen=True)
class StreetGrid:
    """Street centre lines: x = xs[i] (north-south streets) and y = ys[j] (east-west streets)."""

    xs: np.ndarray  # (I,) float64, increasing x of north-south streets, m
    ys: np.ndarray  # (J,) float64, increasing y of east-west streets, m
    road_half: float  # m, half-width of the carriageway (kerb to centre line)
    sidewalk: float  # m, sidewalk width from the kerb to the building line


@dataclass(frozen=True)
class Trajectory:
    """Ego vehicle poses at the frames (vehicle frame: origin on the ground, x forward, z up)."""

    xy: np.ndarray  # (M, 2) float64 world position, m
    yaw: np.ndarray  # (M,) float64 heading, rad
    speed: np.ndarray  # (M,) float64 forward speed, m/s
    yaw_rate: np.ndarray  # (M,) float64, rad/s
    time: np.ndarray  # (M,) float64 frame time from the start of the sequence, s
    route_xy: np.ndarray  # (K, 2) float64 dense route samples (every ~1 m), for scene layout
    route_dir: np.ndarray  # (K, 2) float64 unit travel direction at those samples


def make_grid(rng: np.random.Generator, block: tuple[float, float], extent: float) -> StreetGrid:
    """Random street grid covering [-extent, extent]^2; block lengths uniform in ``block``."""
    road_half = float(rng.uniform(4.0, 6.5))
    sidewalk = float(rng.uniform(2.0, 4.0))

    def lines() -> np.ndarray:
        n = int(np.ceil(extent / block[0])) + 2
        pos = np.cumsum(rng.uniform(block[0], block[1], size=2 * n))  # (2n,) line positions
        return pos - pos[n]  # line n at 0

    return StreetGrid(lines(), lines(), road_half, sidewalk)


_DIRS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])  # E, N, W, S


def _node_xy(grid: StreetGrid, node: tuple[int, int]) -> np.ndarray:
    return np.array([grid.xs[node[0]], grid.ys[node[1]]])


def plan_route(
    rng: np.random.Generator, grid: StreetGrid, length: float, loop: bool
) -> list[tuple[np.ndarray, int]]:
    """Intersections of a route: a list of (node position (2,), heading index 0..3 after it).

    The first entry is the start (mid-block), then one per intersection until the route is at
    least ``length`` m long. ``loop``: the first four intersections all turn the same way.
    """
    ni, nj = len(grid.xs), len(grid.ys)
    node = (ni // 2, nj // 2)
    heading = int(rng.integers(4))
    turn_dir = 1 if rng.random() < 0.5 else -1  # +1 left, -1 right
    # start half-way between the previous intersection and `node`
    prev = (node[0] - int(_DIRS[heading][0]), node[1] - int(_DIRS[heading][1]))
    start = 0.5 * (_node_xy(grid, prev) + _node_xy(grid, node))
    route = [(start, heading)]
    total = float(np.linalg.norm(_node_xy(grid, node) - start))
    k = 0
    while total < length:
        turn = turn_dir if loop and k < 4 else int(rng.choice([0, 0, 1, -1]))
        for tr in (turn, 0, 1, -1):  # stay inside the grid
            nxt = (heading + tr) % 4
            step = (node[0] + int(_DIRS[nxt][0]), node[1] + int(_DIRS[nxt][1]))
            if 0 < step[0] < ni - 1 and 0 < step[1] < nj - 1:
                break
        route.append((_node_xy(grid, node), nxt))
        total += float(np.linalg.norm(_node_xy(grid, step) - _node_xy(grid, node)))
        node, heading = step, nxt
        k += 1
    route.append((_node_xy(grid, node), heading))
    return route


def _lane_polyline(grid: StreetGrid, route: list[tuple[np.ndarray, int]]) -> np.ndarray:
    """Corner points (K, 2) of the right-hand lane path through the route's intersections."""
    off = LANE_OFFSET * grid.road_half
    pts = []
    for idx, (pos, heading) in enumerate(route):
        d_out = _DIRS[heading]
        right_out = np.array([d_out[1], -d_out[0]])
        if idx == 0 or idx == len(route) - 1:
            pts.append(pos + off * right_out)
            continue
        d_in = _DIRS[route[idx - 1][1]]
        right_in = np.array([d_in[1], -d_in[0]])
        if heading == route[idx - 1][1]:
            continue  # straight on: no corner
        pts.append(pos + off * right_in + off * right_out)  # where both lane lines cross
    return np.array(pts)


def _sample_path(
    corners: np.ndarray, radii: np.ndarray, ds: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense samples of a polyline with circular fillets at its inner corners.

    corners: (K, 2); radii: (K,) fillet radius per corner (ends unused); ds: spacing, m.
    Returns xy (S, 2), tangent angle (S,), curvature (S,) (1/m, + left).
    """
    xy_parts, yaw_parts, kap_parts = [], [], []
    cur = corners[0]
    for k in range(1, len(corners)):
        a, b = corners[k - 1], corners[k]
        seg_dir = (b - a) / np.linalg.norm(b - a)
        end = b
        arc = None
        if k < len(corners) - 1:
            nxt_dir = (corners[k + 1] - b) / np.linalg.norm(corners[k + 1] - b)
            cross = seg_dir[0] * nxt_dir[1] - seg_dir[1] * nxt_dir[0]
            ang = np.arctan2(cross, float(seg_dir @ nxt_dir))  # signed turn angle
            tan_len = radii[k] * np.tan(abs(ang) / 2)
            end = b - tan_len * seg_dir
            arc = (ang, radii[k], b + tan_len * nxt_dir)
        n = max(int(np.ceil(np.linalg.norm(end - cur) / ds)), 1)
        s = np.arange(n)[:, None] / n  # (n, 1)
        xy_parts.append(cur + s * (end - cur))
        yaw_parts.append(np.full(n, np.arctan2(seg_dir[1], seg_dir[0])))
        kap_parts.append(np.zeros(n))
        if arc is not None:
            ang, rad, arc_end = arc
            normal = np.array([-seg_dir[1], seg_dir[0]]) * np.sign(ang)  # towards the centre
            centre = end + rad * normal
            m = max(int(np.ceil(abs(ang) * rad / ds)), 1)
            th0 = np.arctan2(end[1] - centre[1], end[0] - centre[0])
            th = th0 + ang * np.arange(m) / m  # (m,)
            xy_parts.append(centre + rad * np.stack([np.cos(th), np.sin(th)], axis=1))
            yaw_parts.append(np.arctan2(seg_dir[1], seg_dir[0]) + ang * np.arange(m) / m)
            kap_parts.append(np.full(m, np.sign(ang) / rad))
            cur = arc_end
        else:
            cur = end
    xy_parts.append(corners[-1][None, :])
    yaw_parts.append(yaw_parts[-1][-1:])
    kap_parts.append(np.zeros(1))
    return np.concatenate(xy_parts), np.unwrap(np.concatenate(yaw_parts)), np.concatenate(kap_parts)


def drive(rng: np.random.Generator, grid: StreetGrid, n_frames: int, loop: bool, cruise: float) -> Trajectory:
    """Plan a route and drive it: ``n_frames`` poses at 10 Hz.

    Speed: ``cruise`` m/s on straights, at most sqrt(2.0 m/s^2 * R) in turns, accelerating at
    1.5 m/s^2 and braking at 2.5 m/s^2; ~30 % of intersections get a stop of 1-4 s before them.
    """
    duration = n_frames * FRAME_DT
    route = plan_route(rng, grid, 1.2 * cruise * duration + 80.0, loop)
    corners = _lane_polyline(grid, route)
    radii = np.where(rng.random(len(corners)) < 0.5, 7.0, 9.0)
    ds = 0.05
    xy, yaw, kappa = _sample_path(corners, radii, ds)
    s = np.arange(len(xy)) * ds  # (S,) arc length (approximately uniform)
    vmax = np.minimum(cruise, np.sqrt(2.0 / np.maximum(np.abs(kappa), 1e-6)))
    # stops: before some corners (where the fillet starts)
    stops: list[tuple[int, float]] = []
    turn_start = np.flatnonzero((np.abs(kappa[1:]) > 0) & (kappa[:-1] == 0)) + 1
    for i in turn_start:
        if rng.random() < 0.3 and i * ds > 15.0:
            j = max(int(i - 4.0 / ds), 0)
            vmax[j] = 0.0
            stops.append((j, float(rng.uniform(1.0, 4.0))))
    v = vmax.copy()
    for i in range(len(v) - 2, -1, -1):  # braking limit
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * 2.5 * ds))
    for i in range(1, len(v)):  # acceleration limit
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * 1.5 * ds))
    dt = ds / np.maximum(0.5 * (v[1:] + v[:-1]), 1e-3)  # (S-1,)
    t = np.concatenate([[0.0], np.cumsum(dt)])  # (S,) time at each sample
    for j, dwell in stops:
        t[j + 1 :] += dwell
    # insert the dwell as a plateau: sample j reached at t[j], left at t[j] + dwell
    t_knots = np.concatenate([t, [t[j] + d for j, d in stops]])
    s_knots = np.concatenate([s, [s[j] for j, _ in stops]])
    order = np.lexsort((s_knots, t_knots))
    t_knots, s_knots = t_knots[order], s_knots[order]
    frame_t = np.arange(n_frames) * FRAME_DT
    if t_knots[-1] < frame_t[-1]:
        raise RuntimeError("route too short for the requested frames")  # guarded by length
    sf = np.interp(frame_t, t_knots, s_knots)  # (M,) arc length at each frame
    idx = np.clip(np.round(sf / ds).astype(np.int64), 0, len(xy) - 1)
    w = np.interp(sf, s, np.arange(len(s)))  # fractional sample index
    pos = np.stack(
        [np.interp(w, np.arange(len(s)), xy[:, 0]), np.interp(w, np.arange(len(s)), xy[:, 1])], axis=1
    )
    heading = np.interp(w, np.arange(len(s)), yaw)
    moving = np.ones(n_frames, bool)
    for j, dwell in stops:  # standing still during a dwell
        moving &= ~((frame_t > t[j] - 1e-9) & (frame_t < t[j] + dwell))
    speed = np.where(moving, v[idx], 0.0)
    step = max(int(1.0 / ds), 1)
    route_xy = xy[::step]
    route_dir = np.stack([np.cos(yaw[::step]), np.sin(yaw[::step])], axis=1)
    return Trajectory(pos, heading, speed, speed * kappa[idx], frame_t, route_xy, route_dir)


def loop_closures(xy: np.ndarray, min_gap: int = 150, radius: float = 5.0) -> list[tuple[int, int]]:
    """Revisits: (i, j) with j the nearest earlier frame at least ``min_gap`` frames before i
    and within ``radius`` m. xy: (M, 2) positions."""
    out = []
    for i in range(min_gap, len(xy)):
        d = np.linalg.norm(xy[: i - min_gap + 1] - xy[i], axis=1)  # (i - min_gap + 1,)
        j = int(np.argmin(d))
        if d[j] <= radius:
            out.append((i, j))
    return out
