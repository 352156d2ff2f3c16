"""Collation: point clouds -> voxels + rulebooks (numpy/numba, the runtime's code) -> torch.

Contract with the training loop and the exporter:

- :class:`EncoderInput` holds what one :class:`~msdnet.training.nn.encoder.SparseEncoder` call needs:
  raw per-voxel column means (the encoder normalises them itself with the config's
  ``*_feature_norm``, inside its ONNX graph, so the runtime feeds the voxelizer's output as is),
  the int64 rulebooks and the last level's coordinates. ``tensors()`` lists them in the order of
  ``msdnet.runtime.model.onnx_spec.ENCODER.inputs``.
- :func:`collate` turns ``[(radar (N, Cr), lidar (M, Cl)), ...]`` (preprocessed, radar frame,
  columns as ``cfg.radar_columns`` / ``cfg.lidar_columns``) into a :class:`Batch` with the
  encoder inputs of both modalities and the LiDAR occupancy/offset targets at 1/4, 1/2 and 1.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from msdnet.runtime.engine.rulebook import batch_coords, build_encoder_rulebooks
from msdnet.runtime.engine.voxelize import voxelize
from msdnet.runtime.model.onnx_spec import NUM_DOWN
from msdnet.runtime.spec.grid import GridConfig
from msdnet.training.config import ModelConfig
from msdnet.training.data.targets import make_targets


@dataclass
class EncoderInput:
    """A batch of voxelized clouds for the sparse encoder."""

    features: Tensor  # (V_0, F) float32 raw per-voxel means of the point columns
    subm: list[Tensor]  # per level l = 0..3: (V_l, 27) int64 rows of level l, sentinel V_l
    down: list[Tensor]  # per down layer to level l = 1..3: (V_l, 27) int64 rows of level l-1
    bev_coords: Tensor  # (V_3, 4) int64 [b, z, y, x] voxels of the last level (1/8 grid)
    batch_size: int  # clouds in the batch (b = 0 .. batch_size - 1)
    # per level l = 0..3: (V_l, 4) int64 [b, z, y, x] (the published R2LDM scatters level 2)
    level_coords: list[Tensor] = field(default_factory=list)

    def tensors(self) -> tuple[Tensor, ...]:
        """Encoder inputs in ``ENCODER.inputs`` order: features, subm_0, (down_l, subm_l) for
        l = 1..3, bev_coords."""
        out = [self.features, self.subm[0]]
        for level in range(1, NUM_DOWN + 1):
            out += [self.down[level - 1], self.subm[level]]
        return (*out, self.bev_coords)

    def to(self, device: torch.device | str) -> EncoderInput:
        """A copy on ``device``."""
        return EncoderInput(
            self.features.to(device),
            [r.to(device) for r in self.subm],
            [r.to(device) for r in self.down],
            self.bev_coords.to(device),
            self.batch_size,
            [c.to(device) for c in self.level_coords],
        )

    def bev_mask(self, shape_hw: tuple[int, int]) -> Tensor:
        """(B, H8, W8) bool: BEV cells holding at least one last-level voxel (the non-empty set
        Omega_ne of MSDNet Eq. 8 / 14 when this is the LiDAR input)."""
        h, w = shape_hw
        mask = torch.zeros(self.batch_size, h, w, dtype=torch.bool, device=self.bev_coords.device)
        c = self.bev_coords
        mask[c[:, 0], c[:, 2], c[:, 3]] = True
        return mask


@dataclass
class Batch:
    """One training step's data."""

    radar: EncoderInput  # student / R2LDM condition input
    lidar: EncoderInput  # teacher input
    targets: list[tuple[Tensor, Tensor]]  # scales 1/4, 1/2, 1: occ (B, D, H, W) {0, 1},
    # off (B, 3, D, H, W) metres [dx, dy, dz] = mean LiDAR point - voxel centre (0 where empty)
    batch_size: int  # frames in the batch

    def to(self, device: torch.device | str) -> Batch:
        """A copy on ``device``."""
        targets = [(o.to(device), f.to(device)) for o, f in self.targets]
        return Batch(self.radar.to(device), self.lidar.to(device), targets, self.batch_size)


def make_encoder_input(clouds: Sequence[np.ndarray], grid: GridConfig, max_voxels: int) -> EncoderInput:
    """clouds: list of (N_i, C) float32 point arrays [x, y, z, ...] (same C) -> EncoderInput.

    Voxelizes each cloud with ``msdnet.runtime.engine.voxelize`` (per-voxel means, cap ``max_voxels``),
    joins them with ``batch_coords`` and builds every rulebook with ``build_encoder_rulebooks``.
    """
    if not clouds:
        raise ValueError("make_encoder_input needs at least one cloud")
    n_cols = {np.asarray(c).shape[-1] for c in clouds}
    if len(n_cols) != 1:
        raise ValueError(f"all clouds must have the same columns, got widths {sorted(n_cols)}")
    voxels = [voxelize(c, grid, max_voxels) for c in clouds]
    coords = batch_coords([v.coords for v in voxels])  # (V_0, 4) [b, z, y, x]
    feats = np.concatenate([v.features for v in voxels], axis=0)  # (V_0, C), same row order
    rb = build_encoder_rulebooks(coords, grid.shape_zyx, num_down=NUM_DOWN)

    def i64(a: np.ndarray) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.int64))

    return EncoderInput(
        features=torch.from_numpy(np.ascontiguousarray(feats, dtype=np.float32)),
        subm=[i64(r) for r in rb.subm],
        down=[i64(r) for r in rb.down],
        bev_coords=i64(rb.coords[-1]),
        batch_size=len(clouds),
        level_coords=[i64(c) for c in rb.coords],
    )


def collate(samples: Sequence[tuple[np.ndarray, np.ndarray]], cfg: ModelConfig) -> Batch:
    """samples: [(radar (N_i, len(cfg.radar_columns)), lidar (M_i, len(cfg.lidar_columns)))],
    preprocessed, radar frame, metres -> Batch (targets from the LiDAR x, y, z)."""
    if cfg.lidar_columns[:3] != ("x", "y", "z") or cfg.radar_columns[:3] != ("x", "y", "z"):
        raise ValueError("radar_columns and lidar_columns must start with x, y, z")
    radar, lidar = [], []
    for i, (r, li) in enumerate(samples):
        r, li = np.asarray(r, dtype=np.float32), np.asarray(li, dtype=np.float32)
        if r.ndim != 2 or r.shape[1] != len(cfg.radar_columns):
            raise ValueError(f"sample {i}: radar must be (N, {len(cfg.radar_columns)}), got {r.shape}")
        if li.ndim != 2 or li.shape[1] != len(cfg.lidar_columns):
            raise ValueError(f"sample {i}: lidar must be (M, {len(cfg.lidar_columns)}), got {li.shape}")
        radar.append(r)
        lidar.append(li)
    return Batch(
        radar=make_encoder_input(radar, cfg.grid, cfg.max_voxels_radar),
        lidar=make_encoder_input(lidar, cfg.grid, cfg.max_voxels_lidar),
        targets=make_targets([li[:, :3] for li in lidar], cfg.grid),
        batch_size=len(samples),
    )
