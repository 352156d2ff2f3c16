"""Rewrite fields of an exported model's ``manifest.json`` in place, atomically (torch-free: the
calibration commands ``export.gate``, ``export.keep`` and ``export.bands`` use it)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from msdnet.runtime.io.atomic import atomic_output
from msdnet.runtime.model.artifact import MANIFEST


def update_manifest(folder: str | Path, fields: dict[str, Any], drop: tuple[str, ...] = ()) -> Path:
    """Set ``fields`` and remove the keys ``drop`` in ``folder/manifest.json``, written to a
    temporary name and swapped in (``runtime.io.atomic.atomic_output``: a failure leaves the old
    file and raises one line). Only the manifest changes; a signature over it must be made again."""
    path = Path(folder) / MANIFEST
    manifest = json.loads(path.read_text(encoding="utf-8"))
    for key in drop:
        manifest.pop(key, None)
    manifest.update(fields)
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    return path
