"""Named ``.bin`` layouts: the columns of a headerless float32 file whose bytes cannot tell them.

A VoD radar ``.bin`` (7 float32 per row) whose size is a multiple of 112 bytes is also a whole
number of 4-float32 LiDAR rows, so the size alone cannot pick the layout. ``--layout NAME`` (or
``--columns x,y,z,...``) names it; without either, ``msdnet-infer`` reads a ``.bin`` with the
layout of the data the model was trained on (``input.layout`` in the manifest, written at export
by :func:`layout_for_columns`); a manifest without that key keeps the older rule (the path, then
the size; ``runtime/io/files.read_cloud``).

Layouts (rows of little-endian float32):

- ``vod-radar``: ``x y z rcs v_r v_r_compensated time`` (VoD radar; the simulator's radar);
- ``kitti-lidar``: ``x y z intensity`` (KITTI / VoD Velodyne);
- ``astyx-radar``: ``x y z v_r mag`` (the Astyx radar ``.txt`` columns, as float32 rows);
- ``xyz``: ``x y z``; ``xyzi``: ``x y z intensity``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from msdnet.runtime.engine.pointcloud import canonical_column
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.files import LIDAR_COLUMNS, VOD_RADAR_COLUMNS

LAYOUTS: dict[str, tuple[str, ...]] = {
    "vod-radar": VOD_RADAR_COLUMNS,
    "kitti-lidar": LIDAR_COLUMNS,
    "astyx-radar": ("x", "y", "z", "v_r", "mag"),
    "xyz": ("x", "y", "z"),
    "xyzi": ("x", "y", "z", "intensity"),
}
RADAR_LAYOUTS = ("vod-radar", "astyx-radar")  # tried in this order by layout_for_columns
MANIFEST_KEY = "layout"  # manifest["input"][MANIFEST_KEY]: the training data's .bin layout


def layout_for_columns(columns: Sequence[str]) -> str | None:
    """The radar layout holding every model column (the data the model was trained on: VoD and
    the simulator -> ``vod-radar``, Astyx -> ``astyx-radar``); None when none holds them all."""
    for name in RADAR_LAYOUTS:
        if set(columns) <= set(LAYOUTS[name]):
            return name
    return None


def parse_columns(text: str) -> tuple[str, ...]:
    """``"x,y,z,rcs"`` -> canonical column names; MsdnetError naming ``--columns`` when bad."""
    cols = tuple(canonical_column(c) for c in text.split(",") if c.strip())
    if cols[:3] != ("x", "y", "z"):
        raise MsdnetError("--columns", f"must start with x,y,z, got {text!r}")
    if len(set(cols)) != len(cols):
        raise MsdnetError("--columns", f"repeats a column: {text!r}")
    return cols


def resolve_bin_columns(
    layout: str | None, columns: str | None, manifest: dict[str, Any]
) -> tuple[tuple[str, ...] | None, str]:
    """-> (columns every ``.bin`` input is read with, or None for the path/size rule; where they
    came from, for the log). ``--layout`` and ``--columns`` exclude each other."""
    if layout is not None and columns is not None:
        raise MsdnetError("--layout/--columns", "give one of them, not both")
    if columns is not None:
        return parse_columns(columns), "--columns"
    if layout is not None:
        if layout not in LAYOUTS:
            raise MsdnetError("--layout", f"unknown layout {layout!r} (known: {', '.join(LAYOUTS)})")
        return LAYOUTS[layout], f"--layout {layout}"
    recorded = manifest.get("input", {}).get(MANIFEST_KEY)
    if recorded is None:
        return None, "path or size (the manifest records no layout)"
    if recorded not in LAYOUTS:
        raise MsdnetError("manifest.json", f"input.layout {recorded!r} is not a known layout")
    return LAYOUTS[recorded], f"the model's training layout {recorded}"


def columns_for(path: str | Path, bin_columns: tuple[str, ...] | None) -> tuple[str, ...] | None:
    """The ``columns=`` to read ``path`` with: ``bin_columns`` for a ``.bin``, else None (other
    formats name their columns, or take them from their shape)."""
    return bin_columns if Path(path).suffix.lower() == ".bin" else None
