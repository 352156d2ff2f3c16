"""msdnet.export: torch checkpoint -> ONNX graphs + manifest.json (``msdnet-export``; ``main``: its
jobs, ``cli``: the checkpoint export, ``gate``, ``bands``, ``keep``: calibration of a model,
``recover``, ``refresh``: a model's weights read back and exported again).

Python API: ``export_model(model, kind, cfg, out, source, frames=None)`` writes an artifact
folder (verified first when ``frames`` are given); ``msdnet.runtime.Pipeline.from_dir(out)``
runs it without torch.
"""

from __future__ import annotations

from msdnet.export.cli import VerificationFailed, export_model

__all__ = ["VerificationFailed", "export_model"]
