"""msdnet.runtime: the torch-free runtime.

Python API::

    from msdnet.runtime import Pipeline
    pipe = Pipeline.from_dir("path/to/exported-model")  # msdnet-export output
    result = pipe(points)  # (N, C) float32 in the manifest's columns, or a PointCloud
    result.points, result.confidence, result.timings

The public names below are imported on first use (PEP 562), so ``import msdnet.runtime`` stays
cheap for modules that only need the grid or the schedule.
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "Pipeline": "msdnet.runtime.pipeline",
    "Result": "msdnet.runtime.pipeline",
    "Artifact": "msdnet.runtime.artifact",
    "load_artifact": "msdnet.runtime.artifact",
    "PointCloud": "msdnet.runtime.pointcloud",
    "read_cloud": "msdnet.runtime.io",
    "write_cloud": "msdnet.runtime.io",
    "MsdnetError": "msdnet.runtime.errors",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'msdnet.runtime' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
