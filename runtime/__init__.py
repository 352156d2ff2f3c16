"""msdnet.runtime: the torch-free runtime.

Python API::

    from msdnet.runtime import Pipeline
    pipe = Pipeline.from_dir("astyx-lite")  # a shipped model's name, or an msdnet-export folder
    result = pipe(points)  # (N, C) float32 in the manifest's columns, or a PointCloud
    result.points, result.confidence, result.timings

Sub-packages, each importing only those before it (tests/test_import_graph.py checks): ``errors``
(``MsdnetError``, the extras), ``spec`` (grid, diffusion schedules, range thresholds), ``model``
(the exported artifact: manifest, ONNX specs and checks, shipped models by name, signing),
``providers`` (engine choice and sessions), ``engine`` (voxelizer, rulebooks, decode, the
Pipeline): together the core; then ``io`` (files, layouts, datasets, bags, Rerun, pictures, bag
pairing), ``metrics`` and ``sim`` (the simulator), and ``frontends`` (``msdnet-infer``,
``msdnet-node``, ``msdnet-data``).

The public names below are imported on first use (PEP 562), so ``import msdnet.runtime`` stays
cheap for modules that only need the grid or the schedule. Importing it turns the telemetry of
onnxruntime and OpenVINO off for the process, whatever the environment (``offline.py``).
"""

from __future__ import annotations

import importlib
from typing import Any

# Every engine's telemetry off before any engine is imported (runtime/offline.py): every
# msdnet import comes through here first, so the process and its children send nothing.
from msdnet.runtime.offline import telemetry_off  # noqa: E402

telemetry_off()

_LAZY = {
    "Pipeline": "msdnet.runtime.engine.pipeline",
    "Result": "msdnet.runtime.engine.pipeline",
    "Artifact": "msdnet.runtime.model.artifact",
    "load_artifact": "msdnet.runtime.model.artifact",
    "PointCloud": "msdnet.runtime.engine.pointcloud",
    "read_cloud": "msdnet.runtime.io.files",
    "write_cloud": "msdnet.runtime.io.files",
    "MsdnetError": "msdnet.runtime.errors",
    "files_to_bag": "msdnet.runtime.io.rosbag",  # point-cloud files -> a ROS 2 bag ([ros] extra)
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'msdnet.runtime' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
