"""Bird's-eye-view pictures of point clouds (matplotlib Agg, no display needed).

Radar frame: x forward is drawn upward, y left is drawn to the left (the view from above with
the car driving up the page). The grid box and the radar's field of view are outlined.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from msdnet.runtime.engine.grid import GridConfig
from msdnet.runtime.io.atomic import atomic_output

# one layer: points (N, >=2) [x, y, ...] radar frame, colour, legend label, marker size (pt^2)
Layer = tuple[np.ndarray, str, str, float]


def draw_grid(ax: Any, grid: GridConfig, lw: float, margin: float) -> None:
    """Outline the grid box and the radar's field of view on a BEV axis (x up, y left drawn left),
    and frame the view on the box with ``margin`` (a share of its size) on each side."""
    x0, y0, _, x1, y1, _ = grid.point_range
    ax.add_patch(Rectangle((y0, x0), y1 - y0, x1 - x0, fill=False, ec="tab:blue", lw=lw))
    reach = float(np.hypot(x1, max(abs(y0), abs(y1))))
    for sign in (-1.0, 1.0):
        a = np.radians(grid.fov_deg) * sign
        ax.plot([0.0, reach * np.sin(a)], [0.0, reach * np.cos(a)], "--", c="tab:blue", lw=lw * 2 / 3)
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    ax.set_xlim(y1 + my, y0 - my)  # y left is drawn to the left
    ax.set_ylim(x0 - mx, x1 + mx)


def render_bev(
    path: str | Path,
    layers: Sequence[Layer],
    grid: GridConfig | None = None,
    title: str = "",
    dpi: int = 120,
) -> Path:
    """Draw ``layers`` (first drawn first, so put dense LiDAR before radar) into a PNG.

    The view covers the grid box (with a margin) when ``grid`` is given, else the points.
    Written atomically; returns the path.
    """
    fig = Figure(figsize=(8, 8), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for points, colour, label, size in layers:
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] < 2:
            raise ValueError(f"layer {label!r}: points must be (N, >=2), got {pts.shape}")
        ax.scatter(pts[:, 1], pts[:, 0], s=size, c=colour, label=f"{label} ({len(pts)})", linewidths=0)
    if grid is not None:
        draw_grid(ax, grid, lw=1.2, margin=0.05)
    else:
        ax.invert_xaxis()
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("y (m, left)")
    ax.set_ylabel("x (m, forward)")
    ax.grid(True, lw=0.3, alpha=0.5)
    if title:
        ax.set_title(title, fontsize=10)
    if layers:
        ax.legend(loc="upper right", fontsize=8, markerscale=3)
    target = Path(path)
    with atomic_output(target) as tmp:
        fig.savefig(tmp, format="png")
    return target
