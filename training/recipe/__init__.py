"""How a model is trained and its decoding chosen.

- ``loop``: the training loop (optimiser, schedule, validation, EMA, checkpoints, resume);
- ``checkpoint``: checkpoints without pickle (safetensors + one JSON document);
- ``distributed``: data-parallel training through ``torchrun``;
- ``calibrate``: the occupancy threshold chosen on held-out training-range frames
  (``msdnet-export --calibrate``);
- ``gated_head``: a dense student turned into one with the gated head
  (``msdnet-train gated-head``).
"""
