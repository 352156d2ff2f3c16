"""The torch-free engine: grid, point cloud, voxelizer, rulebooks, sessions, DDIM schedule, decode and
the Pipeline."""
