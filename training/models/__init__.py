"""The trainable models, assembled from ``training.nn``, and their losses.

- ``assembly``: MSDNet's LiDAR teacher and radar student, the R2LDM baseline, ``build_model``;
- ``r2ldm_published``: R2LDM as its authors published it (``--recipe published``);
- ``latent``: the unit-variance latent normalisation measured on the teacher;
- ``losses``: the loss terms of MSDNet and R2LDM, each defined once.
"""
