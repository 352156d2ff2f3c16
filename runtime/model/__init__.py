"""The model artifact a ``msdnet-export`` folder holds, as the engine reads it.

- ``artifact``: ``manifest.json`` (grid, columns, schedule, graphs and their hashes) -> ``Artifact``;
- ``onnx_spec``: the ONNX contract of every graph (tensor names, shapes, dtypes);
- ``onnx_check``: the external-data check of a graph file, without the ``onnx`` package;
- ``shipped``: the models shipped in ``msdnet.models``, found by name (``astyx-lite``);
- ``signing``: Ed25519 signatures of the manifest (``--sign``, ``--trusted-key``).
"""
