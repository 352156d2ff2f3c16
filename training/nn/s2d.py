"""Teacher-side feature enhancement (MSDNet III-B, the S2D module of Sparse2Dense).

F_l^S (B, C, H8, W8) -> F_l^D (B, C, H8, W8): a small 2D hourglass over the LiDAR BEV map that
fills the gaps between occupied cells before the reconstruction head and before the features
are used as the distillation target.

    stem 3x3 (C -> w) -> s2d_blocks residual blocks                        (1/8 grid)
      -> 3x3 stride 2 (w -> 2w) -> s2d_blocks residual blocks               (1/16 grid)
      -> 2x2 transposed conv (2w -> w), cropped to the skip, concat skip -> 3x3 (2w -> w)
    -> 1x1 (w -> C), added to the input (F^D = F^S + enhancement)

GroupNorm everywhere: no batch statistics, so train and eval (and ONNX) agree at batch 1.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from msdnet.training.config import ModelConfig
from msdnet.training.nn.blocks import group_norm


def conv_norm_relu(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    """3x3 conv (padding 1) -> GroupNorm -> ReLU."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
        group_norm(cout),
        nn.ReLU(),
    )


class ResBlock2d(nn.Module):
    """x -> ReLU(x + GN(conv3x3(ReLU(GN(conv3x3(x)))))), shape kept."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            conv_norm_relu(channels, channels),
            nn.Conv2d(channels, channels, 3, padding=1, bias=False),
            group_norm(channels),
        )

    def forward(self, x: Tensor) -> Tensor:
        """x: (B, C, H, W) -> (B, C, H, W)."""
        return torch.relu(x + self.body(x))


class S2D(nn.Module):
    """Dense BEV enhancement: (B, bev_channels, H8, W8) -> same shape."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c, w, n = cfg.bev_channels, cfg.s2d_channels, cfg.s2d_blocks
        self.stem = nn.Sequential(conv_norm_relu(c, w), *[ResBlock2d(w) for _ in range(n)])
        self.down = nn.Sequential(conv_norm_relu(w, 2 * w, stride=2), *[ResBlock2d(2 * w) for _ in range(n)])
        self.up = nn.Sequential(nn.ConvTranspose2d(2 * w, w, 2, stride=2), group_norm(w), nn.ReLU())
        self.fuse = conv_norm_relu(2 * w, w)
        self.out = nn.Conv2d(w, c, 1)

    def forward(self, x: Tensor) -> Tensor:
        """x: F^S (B, C, H, W) -> F^D (B, C, H, W)."""
        skip = self.stem(x)  # (B, w, H, W)
        deep = self.up(self.down(skip))  # (B, w, 2*ceil(H/2), 2*ceil(W/2))
        deep = deep[:, :, : skip.shape[2], : skip.shape[3]]  # crop odd sizes back to (H, W)
        return x + self.out(self.fuse(torch.cat([skip, deep], dim=1)))
