"""Astyx HiRes2019 object labels: ``groundtruth_obj3d/NNNNNN.json``, one file per frame.

Each file holds ``objects[]`` with ``classname`` (Car, Truck, Bus, Person, Trailer, ...),
``center3d`` (m, radar frame: the radar is Astyx's reference frame), ``dimension3d``
(length, width, height, m), ``orientation_quat`` (read scalar first: ``w, x, y, z``; the
publisher does not document the order, and read this way the boxes of frames 000000-000039 hold
1.8x the non-ground LiDAR points they hold read as ``x, y, z, w``), ``occlusion`` and
``measured_by``. The box's length runs along its own x axis, the width along y, the height
along z; the quaternion turns box axes into radar axes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.datasets.frame import read_json

BOXES_DIR = "groundtruth_obj3d"  # folder of the label files under the dataset root


@dataclass(frozen=True, eq=False)
class Boxes:
    """K oriented 3D boxes in the radar frame (x forward, y left, z up, metres)."""

    centers: np.ndarray  # (K, 3) float64 [x, y, z] box centre
    dims: np.ndarray  # (K, 3) float64 [length, width, height] along the box's x, y, z
    rotations: np.ndarray  # (K, 3, 3) float64: p_radar = R @ p_box + centre
    classes: tuple[str, ...]  # (K,) class names as labelled, e.g. "Car"
    occlusion: np.ndarray  # (K,) int64 occlusion level as labelled (-1 when missing)

    def __len__(self) -> int:
        return len(self.classes)

    def subset(self, mask: np.ndarray) -> Boxes:
        """The boxes where ``mask`` ((K,) bool) is set."""
        m = np.asarray(mask, dtype=bool)
        return Boxes(
            self.centers[m],
            self.dims[m],
            self.rotations[m],
            tuple(c for c, k in zip(self.classes, m, strict=True) if k),
            self.occlusion[m],
        )

    def local(self, xyz: np.ndarray, k: int) -> np.ndarray:
        """xyz (N, >=3) [x, y, z] radar frame -> (N, 3) float64 in box ``k``'s axes, centred."""
        p = np.asarray(xyz, dtype=np.float64)[:, :3] - self.centers[k]
        return p @ self.rotations[k]  # rows: R^T (p - c)

    def contains(self, xyz: np.ndarray, k: int, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: the points of ``xyz`` (N, >=3) inside box ``k`` grown by ``margin`` metres on
        every face (``|local| <= dims / 2 + margin`` per axis, boundary inside)."""
        half = self.dims[k] / 2.0 + margin
        return (np.abs(self.local(xyz, k)) <= half).all(axis=1)

    def corners_bev(self, k: int) -> np.ndarray:
        """(4, 2) float64 [x, y]: the footprint of box ``k`` in the radar frame, in drawing order."""
        ln, wd = self.dims[k, 0] / 2.0, self.dims[k, 1] / 2.0
        local = np.array([[ln, wd, 0.0], [ln, -wd, 0.0], [-ln, -wd, 0.0], [-ln, wd, 0.0]])
        return (local @ self.rotations[k].T + self.centers[k])[:, :2]


def quat_to_matrix(q: np.ndarray | list[float]) -> np.ndarray:
    """Scalar-first unit quaternion ``[w, x, y, z]`` (normalised here) -> (3, 3) float64 rotation."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(np.asarray(q, dtype=np.float64))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def empty_boxes() -> Boxes:
    """No box."""
    return Boxes(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), (), np.zeros(0, np.int64))


def read_astyx_boxes(path: str | Path) -> Boxes:
    """One ``groundtruth_obj3d`` JSON file -> :class:`Boxes` (rules in the module docstring).
    MsdnetError naming the file on a missing field or a non-finite / zero quaternion."""
    path = Path(path)
    doc = read_json(path)
    objects = doc.get("objects") if isinstance(doc, dict) else None
    if not isinstance(objects, list):
        raise MsdnetError(path, "no 'objects' list")
    if not objects:
        return empty_boxes()
    centers, dims, rots, classes, occl = [], [], [], [], []
    for i, obj in enumerate(objects):
        try:
            c = np.asarray(obj["center3d"], dtype=np.float64).reshape(3)
            d = np.asarray(obj["dimension3d"], dtype=np.float64).reshape(3)
            q = np.asarray(obj["orientation_quat"], dtype=np.float64).reshape(4)
            name = str(obj["classname"])
        except (KeyError, TypeError, ValueError):
            raise MsdnetError(path, f"object {i}: needs center3d (3), dimension3d (3), "
                              "orientation_quat (4) and classname") from None  # fmt: skip
        if not (np.isfinite(c).all() and np.isfinite(d).all() and np.isfinite(q).all()) or not q.any():
            raise MsdnetError(path, f"object {i}: non-finite box or zero quaternion")
        centers.append(c)
        dims.append(d)
        rots.append(quat_to_matrix(q))
        classes.append(name)
        occ = obj.get("occlusion", -1)
        occl.append(int(occ) if isinstance(occ, int | float) else -1)
    return Boxes(
        np.stack(centers), np.stack(dims), np.stack(rots), tuple(classes), np.asarray(occl, np.int64)
    )
