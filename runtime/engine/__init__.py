"""The torch-free engine: one radar scan in, a dense point cloud out (numpy, numba, onnxruntime).

- ``grid``: the voxel grid (``GridConfig``, presets); ``pointcloud``: ``PointCloud``, the one
  container every reader returns and the Pipeline takes;
- ``voxelize``, ``rulebook``: the numba voxelizer and the sparse-convolution rulebooks;
  ``kernels``: warms every numba kernel;
- ``ddim``, ``cosine_logsnr``: the diffusion schedules and the DDIM step coefficients;
- ``session``, ``openvino_session``: onnxruntime / OpenVINO sessions; ``provider_auto``: the
  per-graph ``--provider auto`` pick, from ``provider_measure``'s timings (``provider_head``: the
  head pick) and ``provider_cache``'s file;
- ``decode``: occupancy + offsets -> points; ``pipeline``: the ``Pipeline`` that runs them all.
"""
