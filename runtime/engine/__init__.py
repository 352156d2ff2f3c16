"""The torch-free engine: one radar scan in, a dense point cloud out (numpy, numba, onnxruntime).

- ``grid``: the voxel grid (``GridConfig``, presets); ``pointcloud``: ``PointCloud``, the one
  container every reader returns and the Pipeline takes;
- ``voxelize``, ``rulebook``: the numba voxelizer and the sparse-convolution rulebooks;
  ``kernels``: warms every numba kernel;
- ``ddim``, ``cosine_logsnr``: the diffusion schedules and the DDIM step coefficients;
- ``session``, ``openvino_session``, ``provider_auto``: onnxruntime / OpenVINO sessions and the
  per-graph ``--provider auto`` pick;
- ``decode``: occupancy + offsets -> points; ``pipeline``: the ``Pipeline`` that runs them all.
"""
