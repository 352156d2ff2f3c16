"""msdnet.training: the torch side that makes the shipped models (``msdnet-train``).

Layers, each importing only those before it (``tests/test_import_graph.py``):

- ``published_config``, ``config``: the model and training configs (frozen dataclasses, presets);
- ``data``: datasets for torch over the runtime's readers, augmentation, batches, targets;
- ``nn``: the networks: sparse encoder, RGFD, noise adapter, light denoiser, R2LDM U-Nets, S2D and
  the reconstruction heads;
- ``models``: the teacher, the student and R2LDM assembled from them, their losses and latents;
- ``recipe``: the training loop, checkpoints, data-parallel runs, threshold calibration and the
  gated head;
- ``cli``: ``msdnet-train`` (also ``torchrun -m msdnet.training.cli``).
"""
