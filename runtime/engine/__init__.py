"""The torch-free engine: one radar scan in, a dense point cloud out (numpy, numba, onnxruntime).

- ``pointcloud``: ``PointCloud``, the one container every reader returns and the Pipeline takes;
- ``voxelize``, ``rulebook``, ``pairs``: the numba voxelizer and the sparse-convolution rulebooks
  (or pairs); ``kernels``: warms every numba kernel;
- ``decode``: occupancy + offsets -> points; ``pipeline``: the ``Pipeline`` that runs them all on
  the sessions ``providers`` opens, with the grid and schedule of ``spec``.
"""
