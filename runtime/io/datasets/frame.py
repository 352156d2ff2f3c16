"""One paired radar + LiDAR frame, everything in the radar frame; small helpers for readers."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.engine.pointcloud import PointCloud, transform_xyz
from msdnet.runtime.errors import MsdnetError


@dataclass(frozen=True, eq=False)
class Frame:
    """A radar scan and the LiDAR sweep paired with it (radar frame: x forward, y left, z up)."""

    frame_id: str  # the dataset's frame id, e.g. "00549" (VoD) or "000000" (Astyx)
    radar: PointCloud  # radar points in the radar frame
    lidar: PointCloud  # LiDAR points already moved INTO the radar frame
    pose: np.ndarray | None  # (4, 4) float64: radar frame -> world/odom frame, None if unknown
    radar_to_lidar: np.ndarray  # (4, 4) float64: p_lidar = radar_to_lidar @ p_radar
    lidar_rig: str = "hdl64"  # LiDAR kind, picks the ground-removal preset (preprocess.py)

    @property
    def lidar_to_radar(self) -> np.ndarray:
        """(4, 4) float64: p_radar = lidar_to_radar @ p_lidar."""
        return np.linalg.inv(self.radar_to_lidar)

    def lidar_in_own_frame(self) -> np.ndarray:
        """(N, 3) float64 [x, y, z]: the LiDAR points back in the LiDAR's own frame."""
        return transform_xyz(self.lidar.xyz, self.radar_to_lidar)


def read_json(path: Path) -> Any:
    """Parse a JSON file; MsdnetError naming the file when missing or broken.

    Files holding several JSON documents one after another (the VoD pose files hold three, one
    per line) are returned as a list of the documents.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MsdnetError(path, "file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise MsdnetError(path, f"cannot read file ({err})") from None
    decoder = json.JSONDecoder()
    docs: list[Any] = []
    pos = 0
    try:
        while True:
            while pos < len(text) and text[pos].isspace():
                pos += 1
            if pos >= len(text):
                break
            doc, pos = decoder.raw_decode(text, pos)
            docs.append(doc)
    except json.JSONDecodeError as err:
        raise MsdnetError(path, f"broken JSON: {err.msg} at line {err.lineno}") from None
    if not docs:
        raise MsdnetError(path, "empty JSON file")
    return docs[0] if len(docs) == 1 else docs


def as_transform(value: Any, path: Path, what: str) -> np.ndarray:
    """A 4x4 (or 3x4, completed with [0 0 0 1]) row-major matrix -> (4, 4) float64."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise MsdnetError(path, f"{what} is not a numeric matrix") from None
    if m.size == 12:
        m = np.vstack([m.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    if m.size != 16:
        raise MsdnetError(path, f"{what} must have 12 or 16 numbers, got {m.size}")
    m = m.reshape(4, 4)  # row-major
    if not np.isfinite(m).all() or abs(np.linalg.det(m[:3, :3]) - 1.0) > 1e-2:
        raise MsdnetError(path, f"{what} is not a rigid transform")
    return m


class FrameDataset:
    """Common surface of the readers: ``frame_ids``, ``len``, ``ds[i]``, ``ds.get(id)``, iteration.

    Subclasses set ``self.frame_ids`` and implement ``load(frame_id) -> Frame``.
    """

    root: Path
    frame_ids: list[str]

    def load(self, frame_id: str) -> Frame:
        raise NotImplementedError

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __getitem__(self, index: int) -> Frame:
        return self.load(self.frame_ids[index])

    def __iter__(self) -> Iterator[Frame]:
        for frame_id in self.frame_ids:
            yield self.load(frame_id)

    def get(self, frame_id: str) -> Frame:
        """The frame with that id; MsdnetError (naming the dataset folder) when unknown."""
        if frame_id not in self.frame_ids:
            have = f"{self.frame_ids[0]}..{self.frame_ids[-1]}" if self.frame_ids else "none"
            raise MsdnetError(self.root, f"no frame {frame_id!r} ({len(self.frame_ids)} frames: {have})")
        return self.load(frame_id)


def _order_key(frame_id: str) -> tuple[int, int | str]:
    return (0, int(frame_id)) if frame_id.isdigit() else (1, frame_id)


def split_contiguous(
    ids: list[str], val_fraction: float = 0.2, blocks: int = 1, gap: int = 0
) -> tuple[list[str], list[str]]:
    """Train/val split by contiguous frame ranges, never at random.

    Frames of one drive are near-duplicates of their neighbours, so a random split leaks.
    The ids (sorted numerically when they are numbers) are cut into ``blocks`` equal contiguous
    chunks; the last ``round(val_fraction * len(chunk))`` frames of each chunk go to val, and
    the ``gap`` frames just before each val range are dropped from both sides.
    Returns ``(train_ids, val_ids)``, each in frame order.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    if blocks < 1 or gap < 0:
        raise ValueError(f"blocks must be >= 1 and gap >= 0, got {blocks}, {gap}")
    ordered = sorted(ids, key=_order_key)
    train: list[str] = []
    val: list[str] = []
    for chunk in np.array_split(np.arange(len(ordered)), blocks):  # contiguous index ranges
        n_val = int(round(val_fraction * len(chunk)))
        n_train = max(len(chunk) - n_val - gap, 0)
        train += [ordered[i] for i in chunk[:n_train]]
        val += [ordered[i] for i in chunk[len(chunk) - n_val :]]
    return train, val
