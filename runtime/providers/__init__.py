"""Engine choice: which library runs each graph, and its sessions.

- ``session``: onnxruntime sessions and the ``--provider`` names; ``openvino_session``: OpenVINO
  behind the same interface (the ``openvino`` extra);
- ``provider_auto``: the per-graph ``--provider auto`` pick, from ``provider_measure``'s timings
  (``provider_agree``: outputs within the export tolerances; ``provider_budget``: how long
  measuring may take; ``provider_head``: the head pick) and ``provider_cache``'s file.
"""
