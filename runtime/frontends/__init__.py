"""The front-ends: the commands, built on the engine, the model artifact and the readers/writers.

- ``densify``: ``DensifyOptions``, the one typed set of options every front-end builds once,
  and ``densify``, the one Pipeline call they all make with it;
- ``model_args``: the model a front-end runs (``--model`` or the bundled one) and the checks of
  ``--provider``, ``--threshold``, ``--steps`` against it;
- ``infer``: ``msdnet-infer`` and its modes; ``live``: ``msdnet-node`` (ROS 2 over DDS);
  ``data``: ``msdnet-data`` (simulate, show, stats, pair).

Nothing below ``frontends`` (engine, model, io, sim) imports it.
"""
