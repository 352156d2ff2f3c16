"""Warm-up of every numba kernel of the runtime: the voxelizer, the rulebook builder, the decoders.

Each module warms its own kernels (``voxelize.warmup``, ``rulebook.warmup``, ``decode.warmup``);
this module calls them all, so none of them imports another only to warm it.
"""

from __future__ import annotations

from msdnet.runtime.engine import decode, pairs, rulebook, voxelize


def warmup() -> None:
    """Compile (or load from numba's cache) every runtime kernel with tiny inputs."""
    voxelize.warmup()
    rulebook.warmup()
    pairs.warmup()
    decode.warmup()
