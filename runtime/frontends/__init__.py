"""The front-ends: ``msdnet-infer`` (``infer``), ``msdnet-node`` (``live``), ``msdnet-data`` (``data``)."""
