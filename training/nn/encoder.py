"""Sparse voxel encoder (MSDNet Eq. 1): VFE -> sparse 3D backbone -> height collapse -> BEV F^S.

Teacher (LiDAR) and student (radar) each own one, with separate weights (MSDNet III-A).

1. Input: per-voxel means of the point columns ``(V_0, F)`` (raw, as the voxelizer returns them).
   The first op normalises them with the config's fixed ``(shift, scale)`` per column, so the
   runtime feeds raw means and the normalisation travels inside ``encoder.onnx``.
2. VFE (VoxelNet-style, one voxel at a time): Linear -> LayerNorm -> ReLU to ``vfe_channels``.
3. Backbone (SECOND-like): a submanifold block at level 0, then three times a stride-2 down
   block and a submanifold block; widths ``encoder_channels`` at 1, 1/2, 1/4, 1/8 of the grid.
4. Height collapse: the level-3 voxels are scattered into a dense ``(B, C, D8, H8, W8)`` volume,
   re-read as ``(B, C * D8, H8, W8)`` (channel-major) and mixed by a 1x1 conv to ``bev_channels``.

The forward takes plain tensors in the order of ``msdnet.runtime.model.onnx_spec.ENCODER.inputs`` so
it traces to ONNX (Gather + Reshape + MatMul per layer, ScatterND for the BEV scatter) with
dynamic voxel counts.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from msdnet.runtime.engine.rulebook import level_shapes
from msdnet.runtime.model.onnx_spec import NUM_DOWN
from msdnet.training.config import ModelConfig
from msdnet.training.data.batch import EncoderInput
from msdnet.training.nn.sparse import SparseConvBlock

__all__ = ["SparseEncoder", "level_shapes"]  # level_shapes lives in runtime.engine.rulebook (torch-free)


class SparseEncoder(nn.Module):
    """Voxels + rulebooks -> BEV features ``(B, bev_channels, H8, W8)``."""

    def __init__(self, cfg: ModelConfig, modality: str) -> None:
        super().__init__()
        if modality not in ("radar", "lidar"):
            raise ValueError(f"modality must be 'radar' or 'lidar', got {modality!r}")
        norm = cfg.radar_feature_norm if modality == "radar" else cfg.lidar_feature_norm
        self.in_features = len(norm)
        shift, scale = zip(*norm, strict=True)
        self.register_buffer("shift", torch.tensor(shift, dtype=torch.float32), persistent=False)
        self.register_buffer("scale", torch.tensor(scale, dtype=torch.float32), persistent=False)
        self.vfe = nn.Sequential(
            nn.Linear(self.in_features, cfg.vfe_channels),
            nn.LayerNorm(cfg.vfe_channels),
            nn.ReLU(),
        )
        ch = cfg.encoder_channels
        self.subm = nn.ModuleList([SparseConvBlock(cfg.vfe_channels, ch[0])])
        self.down = nn.ModuleList()
        for level in range(1, NUM_DOWN + 1):
            self.down.append(SparseConvBlock(ch[level - 1], ch[level], down=True))
            self.subm.append(SparseConvBlock(ch[level], ch[level]))
        self.bev_shape = level_shapes(cfg.grid)[-1]  # (D8, H8, W8)
        self.out_channels = ch[-1]
        self.to_bev = nn.Conv2d(ch[-1] * self.bev_shape[0], cfg.bev_channels, kernel_size=1)

    def forward(
        self,
        voxel_features: Tensor,
        subm_rules_0: Tensor,
        down_rules_1: Tensor,
        subm_rules_1: Tensor,
        down_rules_2: Tensor,
        subm_rules_2: Tensor,
        down_rules_3: Tensor,
        subm_rules_3: Tensor,
        bev_coords: Tensor,
    ) -> Tensor:
        """One frame, the ``encoder.onnx`` graph: voxel_features (V_0, F) raw per-voxel column
        means; subm_rules_l (V_l, 27) int64; down_rules_l (V_l, 27) int64 rows of level l-1;
        bev_coords (V_3, 4) int64 [b = 0, z, y, x]. Returns F^S (1, bev_channels, H8, W8)."""
        return self.run(
            voxel_features, subm_rules_0, down_rules_1, subm_rules_1, down_rules_2, subm_rules_2,
            down_rules_3, subm_rules_3, bev_coords, batch_size=1,
        )  # fmt: skip

    def run(
        self,
        voxel_features: Tensor,
        subm_rules_0: Tensor,
        down_rules_1: Tensor,
        subm_rules_1: Tensor,
        down_rules_2: Tensor,
        subm_rules_2: Tensor,
        down_rules_3: Tensor,
        subm_rules_3: Tensor,
        bev_coords: Tensor,
        batch_size: int,
    ) -> Tensor:
        """Like :meth:`forward` for a batch: bev_coords b in 0..batch_size-1 ->
        F^S (batch_size, bev_channels, H8, W8)."""
        x = self.vfe((voxel_features - self.shift) / self.scale)  # (V_0, vfe)
        x = self.subm[0](x, subm_rules_0)  # (V_0, c0)
        downs = (down_rules_1, down_rules_2, down_rules_3)
        subms = (subm_rules_1, subm_rules_2, subm_rules_3)
        for level in range(NUM_DOWN):
            x = self.down[level](x, downs[level])  # (V_{l+1}, c_{l+1})
            x = self.subm[level + 1](x, subms[level])
        return self.to_bev(self.scatter_bev(x, bev_coords, batch_size))

    def scatter_bev(self, feats: Tensor, coords: Tensor, batch_size: int) -> Tensor:
        """feats (V_3, C), coords (V_3, 4) [b, z, y, x] -> (B, C * D8, H8, W8), channel-major."""
        d8, h8, w8 = self.bev_shape
        c = feats.shape[1]
        lin = ((coords[:, 0] * d8 + coords[:, 1]) * h8 + coords[:, 2]) * w8 + coords[:, 3]  # (V_3,)
        dense = feats.new_zeros(batch_size * d8 * h8 * w8, c).index_put((lin,), feats)
        dense = dense.reshape(batch_size, d8, h8, w8, c).permute(0, 4, 1, 2, 3)  # (B, C, D8, H8, W8)
        return dense.reshape(batch_size, c * d8, h8, w8)

    def encode(self, inp: EncoderInput) -> Tensor:
        """F^S (B, bev_channels, H8, W8) of a collated :class:`~msdnet.training.data.batch.EncoderInput`."""
        return self.run(*inp.tensors(), batch_size=inp.batch_size)
