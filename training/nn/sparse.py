"""Exact sparse 3D convolution as Gather -> Reshape -> MatMul over a precomputed rulebook.

A rulebook (built by :mod:`msdnet.runtime.engine.rulebook` from voxel coordinates alone) is an
``(M, 27)`` int table: for output voxel ``o`` and kernel tap ``k = (kz*3 + ky)*3 + kx`` it holds
the input row read by that tap, or the sentinel ``V_in`` (number of input rows) where there is
none. The network appends one zero row to the input so the sentinel reads zeros. Submanifold
layers have the same rows in and out (output o reads input at ``o - 1 + k`` per axis); stride-2
down layers read input at ``o*2 - 1 + k``. Both are exactly ``torch.nn.functional.conv3d``
(padding 1) of the densified grid, evaluated at the output sites, with the dense weight
``W.reshape(3, 3, 3, cin, cout).permute(4, 3, 0, 1, 2)``.

The same arithmetic exports to ONNX (opset 19) as Concat + Gather + Reshape + MatMul + Add and
runs with any voxel count. Normalisation is LayerNorm over channels (per voxel): no batch
statistics, so training, eval and the ONNX graph compute the same thing whatever the voxel
count (BatchNorm over a few hundred radar voxels would be noisy and differ between modes).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

KERNEL_TAPS = 27  # 3 x 3 x 3 kernel, tap k = (kz*3 + ky)*3 + kx


class RulebookConv3d(nn.Module):
    """3x3x3 sparse convolution driven by a rulebook; weight (27, cin, cout), bias (cout,)."""

    def __init__(self, cin: int, cout: int, bias: bool = True) -> None:
        super().__init__()
        self.cin = cin
        self.cout = cout
        self.weight = nn.Parameter(torch.empty(KERNEL_TAPS, cin, cout))
        self.bias = nn.Parameter(torch.zeros(cout)) if bias else None
        # LeCun-uniform: variance 1 / fan_in, fan_in = 27 taps x cin.
        bound = math.sqrt(3.0 / (KERNEL_TAPS * cin))
        nn.init.uniform_(self.weight, -bound, bound)

    def forward(self, feats: Tensor, rules: Tensor) -> Tensor:
        """feats: (V_in, cin) float; rules: (M, 27) int64 rows of feats, sentinel V_in -> (M, cout)."""
        padded = torch.cat([feats, feats.new_zeros(1, self.cin)], dim=0)  # (V_in + 1, cin)
        gathered = padded[rules]  # (M, 27, cin)
        cols = gathered.reshape(-1, KERNEL_TAPS * self.cin)  # (M, 27*cin), tap-major
        out = cols @ self.weight.reshape(KERNEL_TAPS * self.cin, self.cout)  # (M, cout)
        if self.bias is not None:
            out = out + self.bias
        return out

    def dense_weight(self) -> Tensor:
        """(cout, cin, 3, 3, 3): the same kernel in ``torch.nn.functional.conv3d`` layout."""
        return self.weight.reshape(3, 3, 3, self.cin, self.cout).permute(4, 3, 0, 1, 2)


class SubMConv3d(RulebookConv3d):
    """Submanifold 3x3x3 convolution: outputs only at the input voxels (rules (V, 27))."""


class SparseDownConv3d(RulebookConv3d):
    """Stride-2 3x3x3 convolution (padding 1): rules (V_out, 27) index rows of the finer level."""


class SparseConvBlock(nn.Module):
    """Rulebook conv -> LayerNorm over channels -> ReLU, per voxel."""

    def __init__(self, cin: int, cout: int, down: bool = False) -> None:
        super().__init__()
        self.conv: RulebookConv3d = SparseDownConv3d(cin, cout) if down else SubMConv3d(cin, cout)
        self.norm = nn.LayerNorm(cout)

    def forward(self, feats: Tensor, rules: Tensor) -> Tensor:
        """feats: (V_in, cin); rules: (M, 27) -> (M, cout)."""
        return torch.relu(self.norm(self.conv(feats, rules)))
