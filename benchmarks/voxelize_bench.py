"""``msdnet-bench voxelize``: numba voxelizer and rulebook builder against the numpy references.

Clouds are synthetic and seeded (no data needed): a radar-like scatter (300 points, 5 columns
x y z rcs v_r) and LiDAR-like surfaces (ground, two facades, car-sized boxes, poles; 4 columns
x y z intensity; 2 cm noise; ~20 % of the points outside the grid) of 1k, 20k and 100k points.
The rulebooks are built for a LiDAR-like cloud capped at 40k voxels on the paper grid; the
decoder runs on the paper grid with 1 % of the voxels occupied. Every figure is the median over
``repeats`` timed calls after one untimed warm-up call (numpy rulebooks/decoder: repeats / 5,
at least 3).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import click
import numpy as np

from msdnet.benchmarks.machine import cpu_model
from msdnet.benchmarks.numpy_reference import (
    decode_numpy,
    down_rulebook_numpy,
    subm_rulebook_numpy,
    voxelize_numpy,
)
from msdnet.runtime.engine.decode import decode_occupancy
from msdnet.runtime.engine.kernels import warmup
from msdnet.runtime.engine.rulebook import batch_coords, build_encoder_rulebooks
from msdnet.runtime.engine.voxelize import voxelize
from msdnet.runtime.errors import one_line_errors
from msdnet.runtime.spec.grid import GRID_PRESETS

POINT_COUNTS = (300, 1000, 20000, 100000)  # points per cloud timed by voxelize
RADAR_POINTS = 300  # clouds up to this size are radar-like, larger ones LiDAR-like
RULEBOOK_VOXELS = 40000  # LiDAR teacher voxels for the rulebook timing (paper grid)
VOXEL_CAP = 60000  # max_voxels in the voxelize timings (the LiDAR teacher's cap)
DECODE_FILL = 0.01  # fraction of occupied voxels in the decoder timing (~40k on the paper grid)


def radar_like_cloud(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 5) float32 [x, y, z, rcs, v_r]: scattered detections over a slightly larger box."""
    xyz = rng.uniform((-1.0, -17.0, -3.0), (34.0, 17.0, 5.0), size=(n, 3))  # (n, 3) [x, y, z]
    rcs = rng.normal(-12.0, 8.0, size=(n, 1))  # dBsm
    vel = rng.normal(0.0, 2.0, size=(n, 1))  # m/s
    return np.concatenate([xyz, rcs, vel], axis=1).astype(np.float32)


def lidar_like_cloud(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 4) float32 [x, y, z, intensity]: points on ground, facades, boxes and poles + noise."""
    kind = rng.choice(5, size=n, p=(0.5, 0.15, 0.15, 0.15, 0.05))
    u = rng.uniform(size=(n, 3))  # (n, 3) surface parameters in [0, 1)
    pts = np.empty((n, 3))  # (n, 3) [x, y, z]
    g = kind == 0  # ground, a little wider than the grid
    pts[g] = np.stack([-2 + 36 * u[g, 0], -18 + 36 * u[g, 1], np.full(g.sum(), -1.6)], axis=1)
    for k, side in ((1, -12.0), (2, 11.0)):  # facades along x
        f = kind == k
        pts[f] = np.stack([36 * u[f, 0] - 2, np.full(f.sum(), side), -1.6 + 7 * u[f, 1]], axis=1)
    b = kind == 3  # eight 4.5 x 1.8 x 1.5 m boxes (parked cars), top and one side
    car = rng.integers(0, 8, size=b.sum())
    cx, cy = 4.0 + 3.5 * car, np.where(car % 2 == 0, -8.0, 7.0)
    top = u[b, 2] < 0.5
    pts[b] = np.stack(
        [
            cx + 4.5 * u[b, 0],
            cy + 1.8 * np.where(top, u[b, 1], 0.0),
            -1.6 + np.where(top, 1.5, 1.5 * u[b, 1]),
        ],
        axis=1,
    )
    p = kind == 4  # twelve poles, 0.2 m wide, 5 m tall
    pole = rng.integers(0, 12, size=p.sum())
    ang = 2 * np.pi * u[p, 0]
    pts[p] = np.stack(
        [2.0 + 2.6 * pole + 0.1 * np.cos(ang), np.where(pole % 2 == 0, -10.0, 9.5) + 0.1 * np.sin(ang),
         -1.6 + 5.0 * u[p, 1]],
        axis=1,
    )  # fmt: skip
    pts += rng.normal(0.0, 0.02, size=pts.shape)
    intensity = rng.uniform(0.0, 1.0, size=(n, 1))
    return np.concatenate([pts, intensity], axis=1).astype(np.float32)


def time_pair(
    numba_fn: Callable[[], object], numpy_fn: Callable[[], object], repeats: int, numpy_repeats: int
) -> tuple[float, float, float, float]:
    """Median wall and thread-CPU ms of both functions, calls interleaved (so a busy machine
    slows both alike), each after one untimed call: (numba wall, numpy wall, numba cpu, numpy cpu).
    CPU time leaves out the time other processes held the core."""
    wall: tuple[list[float], list[float]] = ([], [])
    cpu: tuple[list[float], list[float]] = ([], [])
    numba_fn()
    numpy_fn()
    for i in range(max(repeats, numpy_repeats)):
        for which, fn, count in ((0, numba_fn, repeats), (1, numpy_fn, numpy_repeats)):
            if i >= count:
                continue
            w0, c0 = time.perf_counter(), time.thread_time()
            fn()
            cpu[which].append(time.thread_time() - c0)
            wall[which].append(time.perf_counter() - w0)
    med = [float(np.median(t) * 1e3) for t in (*wall, *cpu)]
    return med[0], med[1], med[2], med[3]


@dataclass(frozen=True)
class BenchRow:
    """One timed case: medians in ms."""

    case: str  # what was timed
    grid: str  # grid preset name
    size: int  # points (voxelize), voxels (rulebooks) or grid cells (decode)
    numba_ms: float  # wall, numba
    numpy_ms: float  # wall, numpy reference
    numba_cpu_ms: float  # thread CPU time, numba
    numpy_cpu_ms: float  # thread CPU time, numpy reference

    @property
    def speedup(self) -> float:
        return self.numpy_ms / self.numba_ms

    @property
    def cpu_speedup(self) -> float:
        return self.numpy_cpu_ms / self.numba_cpu_ms


def run_voxelize_bench(
    repeats: int,
    seed: int = 0,
    point_counts: tuple[int, ...] = POINT_COUNTS,
    rulebook_voxels: int = RULEBOOK_VOXELS,
    grids: tuple[str, ...] = ("lite", "paper"),
    big_grid: str = "paper",
) -> list[BenchRow]:
    """Time voxelize (numba vs numpy) per grid and point count, then on ``big_grid`` the encoder
    rulebooks for a LiDAR-like cloud of ``rulebook_voxels`` voxels and the decoder."""
    warmup()
    rows = []
    for grid_name in grids:
        grid = GRID_PRESETS[grid_name]
        for n in point_counts:
            rng = np.random.default_rng(seed + n)
            pts = radar_like_cloud(n, rng) if n <= RADAR_POINTS else lidar_like_cloud(n, rng)
            t = time_pair(
                lambda pts=pts, g=grid: voxelize(pts, g, VOXEL_CAP),
                lambda pts=pts, g=grid: voxelize_numpy(pts, g, VOXEL_CAP),
                repeats,
                repeats,
            )
            rows.append(BenchRow("voxelize", grid_name, n, *t))

    grid = GRID_PRESETS[big_grid]
    # ~1.6 points per occupied paper voxel in this scene, so this many points reach the cap
    pts = lidar_like_cloud(int(rulebook_voxels * 1.6) + 1000, np.random.default_rng(seed))
    coords = batch_coords([voxelize(pts, grid, rulebook_voxels).coords])  # (V, 4) [b, z, y, x]
    shape = grid.shape_zyx

    def numpy_rulebooks() -> None:
        level, level_shape = coords, shape
        for _ in range(3):
            subm_rulebook_numpy(level, level_shape)
            level, _, level_shape = down_rulebook_numpy(level, level_shape)
        subm_rulebook_numpy(level, level_shape)

    t = time_pair(
        lambda: build_encoder_rulebooks(coords, shape), numpy_rulebooks, repeats, max(3, repeats // 5)
    )
    rows.append(BenchRow("rulebooks (4 subm + 3 down)", big_grid, coords.shape[0], *t))

    rng = np.random.default_rng(seed)
    occ = (rng.uniform(size=shape) < DECODE_FILL).astype(np.float32) * 0.9  # (D, H, W)
    off = rng.uniform(-0.05, 0.05, size=(3, *shape)).astype(np.float32)  # (3, D, H, W)
    t = time_pair(
        lambda: decode_occupancy(occ, off, grid, 0.5),
        lambda: decode_numpy(occ, off, grid, 0.5),
        repeats,
        max(3, repeats // 5),
    )
    rows.append(BenchRow(f"decode ({DECODE_FILL:.0%} occupied)", big_grid, occ.size, *t))
    return rows


def format_table(rows: list[BenchRow]) -> str:
    """A plain-text table of the rows: wall medians and speedup, then the CPU-time speedup."""
    head = (
        f"{'case':<28} {'grid':<6} {'size':>7} {'numba ms':>9} {'numpy ms':>9} {'speedup':>8}"
        f" {'numba cpu':>9} {'numpy cpu':>9} {'cpu speedup':>11}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r.case:<28} {r.grid:<6} {r.size:>7} {r.numba_ms:>9.3f} {r.numpy_ms:>9.3f} {r.speedup:>7.1f}x"
            f" {r.numba_cpu_ms:>9.3f} {r.numpy_cpu_ms:>9.3f} {r.cpu_speedup:>10.1f}x"
        )
    return "\n".join(lines)


@click.command("voxelize")
@click.option(
    "--repeats",
    "-r",
    default=20,
    show_default=True,
    type=click.IntRange(min=1),
    help="timed calls per case",
)
@click.option("--seed", default=0, show_default=True, help="seed of the synthetic clouds")
@one_line_errors
def voxelize_command(repeats: int, seed: int) -> None:
    """Time the numba voxelizer and rulebook builder against the numpy references."""
    load = os.getloadavg()[0]
    click.echo(format_table(run_voxelize_bench(repeats, seed)))
    click.echo(
        "size: points (voxelize), voxels (rulebooks), grid cells (decode). Medians in ms after one "
        "warm-up call; cpu = thread CPU time."
    )
    click.echo(
        f"{cpu_model()}, {os.cpu_count()} logical cores, "
        f"1-min load average {load:.2f} before, {os.getloadavg()[0]:.2f} after"
    )
