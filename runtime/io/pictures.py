"""Bird's-eye-view pictures of point clouds (matplotlib Agg, no display needed).

Radar frame: x forward is drawn upward, y left is drawn to the left (the view from above with
the car driving up the page). The grid box and the radar's field of view are outlined, and only
points inside the grid box are drawn.

Each layer has a style: ``"voxels"`` draws every point as a square one voxel wide, half opaque,
so a dense cloud reads at the density it has (where several heights share a column the square
is darker); ``"dots"`` draws small dots above them (a LiDAR sweep); ``"radar"`` draws small dots
with a white rim above everything else. The legend gives each layer's count, the points drawn (``of``:
also the count before the crop), and ``note`` says what was counted. The counts are also stored
in the PNG as a text chunk (``COUNTS_KEY``: JSON ``{label: count}``), so that a test can hold a
picture's legend against the JSON written beside it (``read_counts``).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from msdnet.runtime.io.atomic import atomic_output
from msdnet.runtime.io.datasets.preprocess import crop_mask
from msdnet.runtime.spec.grid import GridConfig

COUNTS_KEY = "msdnet-counts"  # PNG text chunk: the legend's counts as JSON {label: count}
STYLES = ("voxels", "dots", "radar")
RADAR_COLOUR = "#d62728"


@dataclass(frozen=True)
class Layer:
    """One cloud of a picture: points (N, >=2) [x, y, ...] in the radar frame."""

    points: np.ndarray
    colour: str
    label: str
    style: str = "dots"  # STYLES
    of: int | None = None  # the count before a crop, said in the legend as "M of N"


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


def points_per_metre(fig: Any, ax: Any) -> float:
    """Typographic points (1/72 in) per metre of the axis, once its limits and aspect are set."""
    fig.canvas.draw()  # applies the equal aspect, which shrinks the box
    box = ax.get_window_extent()
    span = abs(np.diff(ax.get_xlim())[0])
    return float(box.width / span * 72.0 / fig.dpi)


def in_box(points: np.ndarray, grid: GridConfig | None) -> np.ndarray:
    """The rows of ``points`` (N, >=2) inside the grid box (x and y; z too where given)."""
    pts = np.asarray(points)
    if grid is None or len(pts) == 0:
        return pts
    if pts.shape[1] >= 3:
        return pts[crop_mask(pts[:, :3], grid, fov=False)]
    x0, y0, _, x1, y1, _ = grid.point_range
    keep = (pts[:, 0] >= x0) & (pts[:, 0] < x1) & (pts[:, 1] >= y0) & (pts[:, 1] < y1)
    return pts[keep]


def _label(layer: Layer, n: int) -> str:
    return f"{layer.label} ({n:,} of {layer.of:,})" if layer.of is not None else f"{layer.label} ({n:,})"


def render_bev(
    path: str | Path,
    layers: Sequence[Layer],
    grid: GridConfig | None = None,
    title: str = "",
    note: str = "",
    dpi: int = 150,
) -> Path:
    """Draw ``layers`` (first drawn first; ``"radar"`` layers always on top) into a PNG.

    The view covers the grid box (with a margin) when ``grid`` is given, else the points; with a
    grid only the points inside its box are drawn and counted. ``note`` goes under the title.
    Written atomically; returns the path.
    """
    fig = Figure(figsize=(7, 7.4), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    fig.subplots_adjust(left=0.09, right=0.98, bottom=0.07, top=0.93)
    drawn = []
    for layer in layers:
        pts = np.asarray(layer.points)
        if pts.ndim != 2 or pts.shape[1] < 2:
            raise ValueError(f"layer {layer.label!r}: points must be (N, >=2), got {pts.shape}")
        if layer.style not in STYLES:
            raise ValueError(f"layer {layer.label!r}: style {layer.style!r} not in {STYLES}")
        drawn.append((layer, in_box(pts, grid)))
    if grid is not None:
        draw_grid(ax, grid, lw=1.2, margin=0.05)
    else:
        every = np.concatenate([p[:, :2] for _, p in drawn]) if drawn else np.zeros((0, 2))
        if len(every):
            lo, hi = every.min(axis=0) - 1.0, every.max(axis=0) + 1.0
            ax.set_xlim(hi[1], lo[1])
            ax.set_ylim(lo[0], hi[0])
    ax.set_aspect("equal", adjustable="box")
    per_m = points_per_metre(fig, ax)
    voxel = grid.voxel_size[0] if grid is not None else 0.2
    counts = {}
    for layer, pts in drawn:
        counts[layer.label] = len(pts)
        label = _label(layer, len(pts))
        if layer.style == "voxels":
            side = max(voxel * per_m, 1.0)
            ax.scatter(pts[:, 1], pts[:, 0], s=side**2, marker="s", c=layer.colour, alpha=0.45,
                       linewidths=0, label=label, zorder=1)  # fmt: skip
        elif layer.style == "dots":
            ax.scatter(pts[:, 1], pts[:, 0], s=0.8, c=layer.colour, linewidths=0, label=label, zorder=2)
        else:
            ax.scatter(pts[:, 1], pts[:, 0], s=3.0, c=layer.colour, edgecolors="white", linewidths=0.25,
                       label=label, zorder=3)  # fmt: skip
    ax.set_xlabel("y (m, left)")
    ax.set_ylabel("x (m, forward)")
    ax.grid(True, lw=0.3, alpha=0.5)
    if title or note:
        ax.set_title("\n".join(t for t in (title, note) if t), fontsize=10)
    if layers:
        legend = ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
        for handle in legend.legend_handles:
            handle.set_sizes([30.0])
            handle.set_alpha(1.0)
    target = Path(path)
    with atomic_output(target) as tmp:
        fig.savefig(tmp, format="png", metadata={COUNTS_KEY: json.dumps(counts)})
    return target


def read_counts(path: str | Path) -> dict[str, int]:
    """The legend's counts a picture was written with (``COUNTS_KEY``); {} where it has none."""
    from PIL import Image

    with Image.open(path) as img:
        text = img.text.get(COUNTS_KEY) if hasattr(img, "text") else None
    return json.loads(text) if text else {}
