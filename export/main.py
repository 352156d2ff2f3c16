"""``msdnet-export``: every export job as a sub-command, loaded when it runs.

- ``checkpoint`` (the default: ``msdnet-export CHECKPOINT --out DIR``): a trained checkpoint ->
  ONNX graphs and a manifest (``cli``);
- ``gate``, ``bands``, ``keep``: calibrate an exported model on held-out frames (the coarse-to-fine
  head's gate, thresholds by range band, the keep rule for radar points), written to its manifest;
- ``recover``: a model's torch weights read back out of its graphs, a checkpoint again;
- ``refresh``: a model's graphs exported again with this exporter, its calibration kept.
"""

from __future__ import annotations

from msdnet.runtime.frontends.commands import Lazy, lazy_group

main = lazy_group(
    "msdnet-export",
    "Export a checkpoint to ONNX graphs and a manifest, and calibrate, recover or refresh an "
    "exported model.\n\n"
    "\b\nmsdnet-export CHECKPOINT --out DIR [OPTIONS]   the checkpoint job, the default\n"
    "msdnet-export checkpoint --help                 its options",
    {
        "checkpoint": Lazy(
            "msdnet.export.cli:main",
            "Export a student (MSDNet) or R2LDM checkpoint to ONNX graphs and a manifest (the default).",
        ),
        "gate": Lazy(
            "msdnet.export.gate:main", "Add the coarse-to-fine head to a model and calibrate its gate."
        ),
        "bands": Lazy(
            "msdnet.export.bands:main",
            "Choose a model's decoding thresholds by range band on held-out frames.",
        ),
        "keep": Lazy(
            "msdnet.export.keep:main", "Choose which input radar points a model keeps, on held-out frames."
        ),
        "recover": Lazy(
            "msdnet.export.recover:main", "Rebuild a checkpoint from an exported model's graphs."
        ),
        "refresh": Lazy(
            "msdnet.export.refresh:main",
            "Re-export a model's graphs with this exporter, its calibration kept.",
        ),
    },
    default="checkpoint",
)
