"""Data for torch: frames read by the runtime's readers, made into training pairs and batches.

- ``datasets``: ``PairDataset`` (frames -> preprocess -> (radar, LiDAR) arrays), the contiguous
  fit / selection / validation splits (``make_splits``, ``run_splits``);
- ``augment``: seeded augmentation applied alike to a frame's radar and LiDAR;
- ``batch``: collation: voxels and rulebooks (the runtime's numba code) -> torch tensors;
- ``targets``: the reconstruction head's ground truth (occupancy and offsets per scale).
"""
