"""The reconstruction head a config names (``ModelConfig.head_kind``), for the student, the
teacher and R2LDM alike."""

from __future__ import annotations

from torch import nn

from msdnet.training.config import ModelConfig
from msdnet.training.nn.head import ReconHead
from msdnet.training.nn.head_gated import GatedReconHead
from msdnet.training.nn.head_sparse import SparseReconHead

HEAD_KINDS = ("dense", "gated", "sparse")  # nn.head, nn.head_gated, nn.head_sparse


def build_head(cfg: ModelConfig) -> nn.Module:
    """The head ``cfg.head_kind`` names: "dense" (:class:`ReconHead`), "gated" (the dense head with
    a fixed-statistics norm at 1/2, :class:`GatedReconHead`) or "sparse" (per-voxel layers below
    1/4, :class:`SparseReconHead`)."""
    if cfg.head_kind == "gated":
        return GatedReconHead(cfg)
    if cfg.head_kind == "sparse":
        return SparseReconHead(cfg)
    if cfg.head_kind == "dense":
        return ReconHead(cfg)
    raise ValueError(f"head_kind must be one of {', '.join(HEAD_KINDS)}, got {cfg.head_kind!r}")
