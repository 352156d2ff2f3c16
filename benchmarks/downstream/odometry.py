"""GICP odometry over a sequence of clouds (small_gicp) and relative pose errors.

Poses are (4, 4) float64 homogeneous transforms. ``T_{k-1,k}`` is frame ``k``'s pose expressed in
frame ``k-1`` (what scan-to-scan registration estimates). Rotation errors are in degrees,
translation errors in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import small_gicp


@dataclass(frozen=True)
class GicpSettings:
    """small_gicp registration settings for sparse radar-scale clouds."""

    downsampling_resolution: float = 0.25  # m: voxel-grid downsampling before registration
    max_correspondence_distance: float = 2.0  # m: farthest accepted nearest neighbour
    max_iterations: int = 30  # Gauss-Newton iterations per pair
    num_threads: int = 1  # registration threads


def register_pair(
    target: np.ndarray, source: np.ndarray, init: np.ndarray, settings: GicpSettings
) -> np.ndarray:
    """(4, 4) T_target_source by GICP; ``target``/``source``: (N, >=3) [x, y, z] metres."""
    if len(target) < 10 or len(source) < 10:
        return init.copy()  # too few points to register: keep the motion prior
    result = small_gicp.align(
        np.ascontiguousarray(target[:, :3], dtype=np.float64),
        np.ascontiguousarray(source[:, :3], dtype=np.float64),
        init_T_target_source=init,
        registration_type="GICP",
        downsampling_resolution=settings.downsampling_resolution,
        max_correspondence_distance=settings.max_correspondence_distance,
        max_iterations=settings.max_iterations,
        num_threads=settings.num_threads,
    )
    return np.asarray(result.T_target_source, dtype=np.float64)


def gicp_odometry(clouds: list[np.ndarray], settings: GicpSettings | None = None) -> list[np.ndarray]:
    """Scan-to-scan GICP: ``len(clouds) - 1`` relative transforms ``T_{k-1,k}``.

    Each registration starts from the previous estimate (constant-velocity prior).
    """
    settings = settings or GicpSettings()
    rel: list[np.ndarray] = []
    prior = np.eye(4)
    for prev, cur in zip(clouds[:-1], clouds[1:], strict=True):
        prior = register_pair(prev, cur, prior, settings)
        rel.append(prior)
    return rel


def relative_from_poses(poses: list[np.ndarray]) -> list[np.ndarray]:
    """Ground-truth ``T_{k-1,k} = inv(pose_{k-1}) @ pose_k`` from world poses (4, 4)."""
    return [np.linalg.inv(a) @ b for a, b in zip(poses[:-1], poses[1:], strict=True)]


def rotation_angle_deg(r: np.ndarray) -> float:
    """Angle of a 3x3 rotation matrix, degrees."""
    c = np.clip((np.trace(r[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


@dataclass(frozen=True)
class RelativeErrors:
    """Relative pose error (RPE) over consecutive frames."""

    translation_m: float  # mean ||t(inv(T_gt) T_est)|| per frame pair, metres
    rotation_deg: float  # mean rotation angle of inv(T_gt) T_est per frame pair, degrees
    translation_pct: float  # sum of translation errors / distance travelled, percent
    pairs: int  # frame pairs scored


def relative_errors(estimated: list[np.ndarray], ground_truth: list[np.ndarray]) -> RelativeErrors:
    """RPE of estimated relative transforms against ground-truth relative transforms."""
    if len(estimated) != len(ground_truth) or not estimated:
        raise ValueError("need the same non-zero number of estimated and true relative transforms")
    t_err, r_err, dist = [], [], 0.0
    for est, gt in zip(estimated, ground_truth, strict=True):
        e = np.linalg.inv(gt) @ est
        t_err.append(float(np.linalg.norm(e[:3, 3])))
        r_err.append(rotation_angle_deg(e))
        dist += float(np.linalg.norm(gt[:3, 3]))
    return RelativeErrors(
        translation_m=float(np.mean(t_err)),
        rotation_deg=float(np.mean(r_err)),
        translation_pct=100.0 * float(np.sum(t_err)) / dist if dist > 0 else float("nan"),
        pairs=len(t_err),
    )
