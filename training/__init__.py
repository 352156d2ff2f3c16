"""msdnet.training: the torch side that makes the shipped models (``msdnet-train``).

Layers, each importing only those before it (``tests/test_import_graph.py``):

- ``published_config``, ``config``: the model and training configs (frozen dataclasses, presets);
- ``data``: datasets for torch over the runtime's readers, augmentation, batches, targets;
- ``nn``: the networks: sparse encoder, RGFD, noise adapter, light denoiser, R2LDM U-Nets, S2D and
  the reconstruction heads;
- ``models``: the teacher, the student and R2LDM assembled from them, their losses and latents;
- ``recipe``: the training loop, checkpoints, data-parallel runs, threshold calibration and the
  gated head;
- ``cli``: the training command (also ``torchrun -m msdnet.training.cli``); ``main``: the
  ``msdnet-train`` group of every training job, which lists them without importing torch.
"""

import os as _os

# OpenMP threads that wait passively: with the default policy each of torch's threads spins at every
# barrier, and on a machine where other processes take a core (a test run, a second training) a
# spinning thread waits for a descheduled one; a lite step then takes 3-6x longer (measured in
# docs/results/training-speed). Read by OpenMP when torch loads it, so set before any torch import
# of this package; a value the user set is kept.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
