"""Dataset readers: one per layout, all returning :class:`Frame` in the radar frame.

- ``VodDataset``: View-of-Delft devkit layout (also what the simulator writes: ``"sim"``);
- ``AstyxDataset``: Astyx HiRes2019 layout;
- ``SimAstyxDataset``: the simulator's Astyx rig (``"sim-astyx"``), read as VoD with Astyx names.

``split_contiguous`` splits train/val by contiguous frame ranges (never at random).
"""

from __future__ import annotations

from pathlib import Path

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.datasets.astyx import AstyxDataset
from msdnet.runtime.io.datasets.frame import Frame, FrameDataset, split_contiguous
from msdnet.runtime.io.datasets.sim_astyx import SimAstyxDataset
from msdnet.runtime.io.datasets.vod import VodDataset

# "sim": simulator output, read as VoD; "sim-astyx": the simulator's Astyx rig (Astyx columns)
DATASET_NAMES = ("vod", "astyx", "sim", "sim-astyx")

__all__ = [
    "DATASET_NAMES",
    "AstyxDataset",
    "Frame",
    "FrameDataset",
    "SimAstyxDataset",
    "VodDataset",
    "open_dataset",
    "split_contiguous",
]


def open_dataset(
    name: str, root: str | Path, split: str | None = None, radar_frames: int = 1
) -> FrameDataset:
    """Open a dataset by name (``vod``, ``astyx``, ``sim`` or ``sim-astyx``); ``radar_frames`` is
    VoD/sim only."""
    if name in ("vod", "sim"):
        return VodDataset(root, split=split, radar_frames=radar_frames)
    if name == "sim-astyx":
        return SimAstyxDataset(root, split=split, radar_frames=radar_frames)
    if name == "astyx":
        if radar_frames != 1:
            raise MsdnetError(root, "Astyx has single radar scans only (radar_frames=1)")
        return AstyxDataset(root, split=split)
    raise MsdnetError(root, f"unknown dataset {name!r} (known: {', '.join(DATASET_NAMES)})")
