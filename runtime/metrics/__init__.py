"""Point-cloud quality metrics, low in the package so that training, the runtime's dataset mode
and the benchmarks score with the same code (numpy and scipy only).

- ``cloud``: our formulas (MSDNet Sec. IV-C; R2LDM Sec. IV): Chamfer distance, modified Hausdorff,
  F-score, BEV JSD and MMD, and ``score_frame`` for all of them at once;
- ``official``: the R2LDM authors' evaluation script's formulas (squared CD as a sum, squared
  Hausdorff, F@0.05 m after voxel-centroid preprocessing; set-level JSD / MMD);
- ``crop``: ``crop_to_grid`` / ``xy_range``, the crop and BEV area every metric scores in.
"""
