"""msdnet.runtime: the torch-free runtime.

Python API::

    from msdnet.runtime import Pipeline
    pipe = Pipeline.from_dir("path/to/exported-model")  # msdnet-export output
    result = pipe(points)  # (N, C) float32 in the manifest's columns, or a PointCloud
    result.points, result.confidence, result.timings

Sub-packages: ``engine`` (voxelizer, rulebooks, sessions, DDIM schedule, decode, the Pipeline),
``model`` (the exported artifact: manifest, ONNX specs and checks, signing), ``io`` (files,
layouts, datasets, bags, Rerun, pictures, bag pairing), ``sim`` (the simulator) and
``frontends`` (``msdnet-infer``, ``msdnet-node``, ``msdnet-data``); ``errors`` holds
``MsdnetError``. Each imports only those before it (engine and model together form the core),
which tests/test_import_graph.py checks.

The public names below are imported on first use (PEP 562), so ``import msdnet.runtime`` stays
cheap for modules that only need the grid or the schedule. Importing it turns onnxruntime's
telemetry off for the process (``ORT_DISABLE_TELEMETRY=1``, ``ORT_TELEMETRY_DISABLED=1``) unless
the environment already sets them.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

# onnxruntime >= 1.29 sends telemetry on Linux and writes a device id under ~/.cache/Microsoft
# unless told not to before it is first imported: every msdnet.runtime import comes through here
# first, so the process runs with it off (a value the user set is kept).
TELEMETRY_OFF = {"ORT_DISABLE_TELEMETRY": "1", "ORT_TELEMETRY_DISABLED": "1"}
for _name, _value in TELEMETRY_OFF.items():
    os.environ.setdefault(_name, _value)
del _name, _value

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
