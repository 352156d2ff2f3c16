"""The dense reconstruction head with a fixed-statistics norm at 1/2, whose coarse-to-fine graph
computes the 1/2 level only where the 1/4 level sees occupancy (``ModelConfig.head_kind``
"gated").

Same layers, weights and contract as :class:`~msdnet.training.nn.head.ReconHead` (a dense checkpoint
loads into it), with one change: the GroupNorm after the 1/2 level's 3x3x3 conv normalises with
fixed per-group statistics (:class:`FixedGroupNorm`) instead of statistics over the whole 1/2
volume, which only the dense conv could give. The norm before the conv keeps its per-frame
statistics: its input is the 2x up-sampling of the 1/4 level, a linear map of the 8,000 (lite)
1/4 voxels' rows, so the sparse graph computes them exactly from those rows' sum and c4 x c4 Gram
matrix. ``training.recipe.gated_head`` sets the fixed
statistics on the training range, and refits the 1/4 occupancy branch so that it says where the
head decodes points (the gate). Every layer below 1/4 is then a function of a voxel's 3x3x3
neighbourhood and of the whole-volume statistics of the up-sampling, so
:meth:`GatedReconHead.sparse` grows the occupied set coarse to fine and gives exactly the dense
values where it computes:

    1/8, 1/4   dense, as ReconHead (lite: 1,200 and 8,000 voxels)          -> x4, occupancy occ4
    1/4 gate   parents P = the 1/4 voxels with occ4 > gate; P+ = P grown by one voxel (3x3x3)
    1/2 input  the GroupNorm statistics of every 1/4 voxel's 8 up-sampled children (from the
               1/4 rows' sum and Gram matrix); the children of P+ up-sampled (rows, one matmul),
               normalised, ReLU
    1/2 conv   per child of P: 3x3x3 conv as a gather of 27 neighbour rows + one matmul
               (a rulebook, as the encoder's; every neighbour is a child of P+, or outside the
               volume: the dense conv's zero padding), norm, ReLU               -> x2, occ2
    full       per child of P with min(occ2, occ4 of its parent) > gate: its 8 children's
               [logit, dx, dy, dz] (``HeadOutputs._row_children``)

With gate 0 every voxel is computed and the outputs equal :meth:`packed`'s.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from msdnet.training.config import ModelConfig
from msdnet.training.nn.head import CHILD_DX, CHILD_DY, CHILD_DZ, ReconHead, rows


class FixedGroupNorm(nn.Module):
    """A GroupNorm whose statistics are fixed: y = x * weight + bias per channel, the same map for
    every voxel. Built from a GroupNorm (its affine as ``weight`` / ``bias``, i.e. statistics 0 / 1)
    and given its statistics by :meth:`fold`, which folds them into ``weight`` and ``bias`` (so
    the state_dict keys are the GroupNorm's, and the exported Mul / Add hold the weights as they are)."""

    def __init__(self, num_groups: int, num_channels: int, eps: float = 1e-5) -> None:
        super().__init__()
        self.num_groups, self.num_channels, self.eps = num_groups, num_channels, eps
        self.weight = nn.Parameter(torch.ones(num_channels))
        self.bias = nn.Parameter(torch.zeros(num_channels))

    def fold(self, mean: Tensor, var: Tensor) -> None:
        """Normalise with per-group ``mean`` (G,) and ``var`` (G,) before the affine already held."""
        per = self.num_channels // self.num_groups
        with torch.no_grad():
            scale = self.weight / torch.sqrt(var.repeat_interleave(per).to(self.weight) + self.eps)
            self.bias.sub_(mean.repeat_interleave(per).to(self.weight) * scale)
            self.weight.copy_(scale)

    def forward(self, x: Tensor) -> Tensor:
        """x (B, C, ...) -> the same shape."""
        shape = (1, -1) + (1,) * (x.dim() - 2)
        return x * self.weight.reshape(shape) + self.bias.reshape(shape)

    def on_rows(self, x: Tensor) -> Tensor:
        """x (..., C), channels last."""
        return x * self.weight + self.bias


def fixed_from(gn: nn.GroupNorm) -> FixedGroupNorm:
    """A FixedGroupNorm with ``gn``'s groups, eps and affine (statistics 0 / 1 until folded)."""
    out = FixedGroupNorm(gn.num_groups, gn.num_channels, gn.eps)
    out.load_state_dict(gn.state_dict())
    return out


class GatedReconHead(ReconHead):
    """ReconHead with a fixed-statistics norm after the 1/2 conv and the coarse-to-fine graph of
    the module docstring."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__(cfg)
        # post2: GroupNorm (exact: statistics of the up-sampled 1/4 rows) -> ReLU -> conv -> this
        self.post2[2][1] = fixed_from(self.post2[2][1])
        for name, v in (("child_dz", CHILD_DZ), ("child_dy", CHILD_DY), ("child_dx", CHILD_DX)):
            self.register_buffer(name, torch.tensor(v, dtype=torch.int64).reshape(1, 8), persistent=False)
        (d4, h4, w4), (d2, h2, w2) = self.shapes[0], self.shapes[1]
        _, _, _, inside = self._children(torch.arange(d4 * h4 * w4))  # every 1/4 voxel's
        self.register_buffer("inside_all", inside.float(), persistent=False)  # (V4, 8) not cropped
        self.cropped = bool(inside.min() == 0)  # lite and paper: 2 x the 1/4 grid is the 1/2 grid
        self.half_count = d2 * h2 * w2  # 1/2 voxels the norm's statistics are over
        k = torch.arange(27)  # tap (kz * 3 + ky) * 3 + kx, neighbour at (z + kz - 1, ...)
        taps = ((k // 9 - 1) * (h2 + 2) + (k // 3 % 3 - 1)) * (w2 + 2) + (k % 3 - 1)
        self.register_buffer("taps", taps.reshape(1, 27), persistent=False)  # in the padded volume

    def _children(self, parents: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """parents (K,) linear 1/4 indices -> their children's 1/2 coordinates z, y, x (K, 8) in
        child order ``(dz * 2 + dy) * 2 + dx``, and (K, 8) bool: inside the 1/2 grid (not cropped)."""
        (_, h4, w4), (d2, h2, w2) = self.shapes[0], self.shapes[1]
        z = torch.div(parents, h4 * w4, rounding_mode="floor").unsqueeze(1) * 2 + self.child_dz
        y = (
            torch.remainder(torch.div(parents, w4, rounding_mode="floor"), h4).unsqueeze(1) * 2
            + self.child_dy
        )
        x = torch.remainder(parents, w4).unsqueeze(1) * 2 + self.child_dx
        return z, y, x, (z < d2) & (y < h2) & (x < w2)

    def fixed_norm(self) -> FixedGroupNorm:
        """The 1/2 level's norm after its 3x3x3 conv, the one with fixed statistics."""
        return self.post2[2][1]

    def _half_input(self, x4: Tensor, par: Tensor) -> Tensor:
        """x4 (1, c4, D4, H4, W4), par (K,) 1/4 voxels -> their 8 children's conv input,
        ReLU(GroupNorm(up2)) (K, 8, c2), exactly the dense volume's.

        The GroupNorm's statistics are over every 1/4 voxel's up-sampled rows u = x W_k + b_k
        (child k; cropped children left out), but u is never formed for all of them: with
        x' = x - mean(x) (centred, so the sums of squares do not cancel), the sums per child and
        channel are S1 W_k + n_k b'_k and diag(W_k^T G_k W_k) + 2 b'_k (S1 W_k) + n_k b'_k^2, where
        S1 = sum x', G = x'^T x' (a c4 x c4 Gram matrix: lite 8,000 x 32 x 32) and b' = mean(x) W + b.
        Only the K parents' rows are then up-sampled (one matmul) and normalised."""
        norm, c2, c4 = self.post2[0], self.up2.cout, self.c4
        x = x4.reshape(c4, -1).t()  # (V4, c4) rows of the 1/4 volume
        shift = x.mean(0)  # (c4,)
        xc = x - shift  # (V4, c4)
        w = self.up2.proj.weight.reshape(8, c2, c4).permute(0, 2, 1)  # (child, c4, c2)
        b = (shift @ w + self.up2.proj.bias.reshape(8, c2)).unsqueeze(1)  # (child, 1, c2) = b'
        if self.cropped:  # per child, only the 1/4 voxels whose child k is inside the 1/2 grid
            m = self.inside_all.t().unsqueeze(2)  # (child, V4, 1)
            s1 = (m * xc).sum(1, keepdim=True)  # (child, 1, c4)
            gram = (m * xc).transpose(1, 2) @ xc  # (child, c4, c4)
            n = m.sum(1, keepdim=True)  # (child, 1, 1)
        else:
            s1 = xc.sum(0).reshape(1, 1, c4)
            gram = (xc.t() @ xc).unsqueeze(0)  # (1, c4, c4)
            n = torch.full((1, 1, 1), float(x.shape[0]))
        s1w = s1 @ w  # (child, 1, c2)
        sum1 = s1w + n * b  # (child, 1, c2) sum of u
        sum2 = ((gram @ w) * w).sum(1, keepdim=True) + 2.0 * b * s1w + n * b * b  # sum of u^2
        g, per = norm.num_groups, c2 // norm.num_groups
        count = self.half_count * per
        mean = sum1.reshape(8, g, per).sum(dim=(0, 2)) / count  # (G,)
        var = torch.clamp(sum2.reshape(8, g, per).sum(dim=(0, 2)) / count - mean * mean, min=0.0)
        scale = norm.weight / torch.sqrt(var + norm.eps).repeat_interleave(per)  # (c2,)
        shift2 = norm.bias - mean.repeat_interleave(per) * scale
        u = rows(self.up2.proj, x.index_select(0, par))  # (K, 8 * c2), column child * c2 + c
        return torch.relu(u.reshape(-1, 8, c2) * scale + shift2)

    def _conv_rows(self, gathered: Tensor) -> Tensor:
        """gathered (M, 27, c2_in) neighbour rows in tap order -> the 3x3x3 conv (M, c2)."""
        conv = self.post2[2][0]
        w = conv.weight.permute(2, 3, 4, 1, 0).reshape(-1, conv.out_channels)  # (27 * cin, cout)
        return gathered.reshape(-1, w.shape[0]) @ w  # not (M, -1): M may be 0

    def sparse(self, features: Tensor, gate: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Coarse-to-fine inference, batch 1 (module docstring), with ``ReconHead.sparse``'s
        outputs: occupancy (N, 8), offsets (N, 8, 3), voxels (N,) increasing half-scale index
        ``(z2 * H2 + y2) * W2 + x2``, gate_occupancy (N,) = min(own 1/2 occupancy, parent's 1/4
        occupancy) > gate. With gate 0 every voxel is kept and the outputs equal :meth:`packed`'s."""
        x4 = self._quarter(features)  # (1, c4, D4, H4, W4)
        occ4 = torch.sigmoid(self.occ[0](x4))  # (1, 1, D4, H4, W4)
        passed = (occ4 > gate).float()
        grown = nn.functional.max_pool3d(passed, 3, stride=1, padding=1)  # P+ : P and its neighbours
        par = torch.nonzero(grown.reshape(-1)).reshape(-1)  # (K,) 1/4 voxels whose children are read
        is_p = passed.reshape(-1).index_select(0, par) > 0  # (K,) in P: its children are computed
        u = self._half_input(x4, par)  # (K, child, c2)
        return self._half_level(par, is_p, u, occ4.reshape(-1).index_select(0, par), gate)

    def _half_level(
        self, par: Tensor, is_p: Tensor, u: Tensor, par_occ: Tensor, gate: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The 1/2 level and the full scale from the K 1/4 voxels ``par`` (P+, increasing linear
        index), ``is_p`` (K,) bool: in P (its children are computed), ``u`` (K, child, c2) their
        children's conv input, ``par_occ`` (K,) the occupancy each passes the gate with (the
        smallest of its own and its ancestors') -> :meth:`sparse`'s outputs."""
        d2, h2, w2 = self.shapes[1]
        c2 = self.up2.cout
        z, y, x, inside = self._children(par)  # (K, 8) each
        inside = inside.reshape(-1)  # (K * 8,) the crop to 1/2's grid
        padded = (((z + 1) * (h2 + 2) + y + 1) * (w2 + 2) + x + 1).reshape(-1)  # (K * 8,)
        zero_row = u.shape[0] * 8  # the table's appended zero row: padding and cropped children
        lookup = torch.full(((d2 + 2) * (h2 + 2) * (w2 + 2),), zero_row, dtype=torch.int64)
        row_id = torch.where(inside, torch.arange(zero_row), torch.full_like(padded, zero_row))
        lookup = lookup.scatter(0, padded, row_id)  # padded 1/2 voxel -> row of the table
        table = torch.cat([u.reshape(-1, c2), torch.zeros(1, c2)], 0)  # (K * 8 + 1, c2)
        child = torch.nonzero(inside & is_p.unsqueeze(1).expand(-1, 8).reshape(-1)).reshape(-1)  # (M,)
        nb = lookup.index_select(0, (padded.index_select(0, child).unsqueeze(1) + self.taps).reshape(-1))
        gathered = table.index_select(0, nb).reshape(-1, 27, c2)  # (M, tap, c2)
        x2 = torch.relu(self.fixed_norm().on_rows(self._conv_rows(gathered)))  # (M, c2)
        occ2 = torch.sigmoid(rows(self.occ[1], x2)).reshape(-1)  # (M,)
        parent = par_occ.unsqueeze(1).expand(-1, 8).reshape(-1)  # (K * 8,)
        gate_occ = torch.minimum(occ2, parent.index_select(0, child))
        keep = torch.nonzero(gate_occ > gate).reshape(-1)
        vox = ((z * h2 + y) * w2 + x).reshape(-1).index_select(0, child)  # (M,) half-scale index
        voxels, order = torch.sort(vox.index_select(0, keep))  # increasing half-scale index
        keep = keep.index_select(0, order)
        occ, off = self._row_children(x2.index_select(0, keep))  # (N, 8), (N, 8, 3)
        return occ, off, voxels, gate_occ.index_select(0, keep)
