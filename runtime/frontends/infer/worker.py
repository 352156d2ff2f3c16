"""The per-file work of ``msdnet-infer``, shared by its local loop, its ``--workers`` processes and
its Ray actors (``frontends/infer/ray_batch``), so that every mode writes the same bytes.

``WORKER`` holds the process's Pipeline and options (``pipe``: the Pipeline, ``options``: the
run's :class:`~msdnet.runtime.frontends.densify.DensifyOptions`); ``_run_one(src, dst)`` reads
one scan, densifies it (``frontends.densify.densify``, the one Pipeline call of every mode),
writes it atomically and returns its summary row, never raising.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from msdnet.runtime.engine.pointcloud import DROP_REASONS
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.densify import DensifyOptions, densify
from msdnet.runtime.frontends.infer.guards import watch_parent
from msdnet.runtime.io.files import read_cloud, write_dense
from msdnet.runtime.io.layouts import columns_for

WORKER: dict[str, Any] = {}  # per-process pipeline and options (worker processes, Ray actors)


def _init_worker(
    model: str, provider: str, threads: int | None, options: DensifyOptions, parent: int, key: str | None
) -> None:
    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.model.artifact import load_artifact

    watch_parent(parent)  # exit when msdnet-infer is killed: no orphaned workers
    WORKER["pipe"] = Pipeline(load_artifact(model, key), provider=provider, threads=threads)
    WORKER["options"] = options


def _run_one(src: str, dst: str) -> dict[str, Any]:
    """Process one file in this process's pipeline; never raises (errors are reported)."""
    pipe, options = WORKER["pipe"], WORKER["options"]
    row: dict[str, Any] = {"file": src, "points_in": 0, "points_out": 0, "seconds": 0.0}
    row |= dict.fromkeys(DROP_REASONS, 0)  # the rows not used, by reason (Result.stats)
    try:
        start = time.perf_counter()
        cloud = read_cloud(src, columns=columns_for(src, options.bin_columns))
        row.update(points_in=len(cloud), dropped_nonfinite=cloud.dropped_nonfinite)
        res = densify(pipe, cloud, options)
        row.update({k: res.stats[k] for k in DROP_REASONS})
        write_dense(dst, res.points, res.confidence, options.fmt)
        if options.png:
            _picture(Path(dst).with_suffix(".png"), cloud.xyz, res.points, pipe.artifact, Path(src).name)
        notes = list(res.notes)
        if len(cloud) == 0 and cloud.dropped_nonfinite:  # not an "empty scan": every row was bad
            notes = [f"all {cloud.dropped_nonfinite} rows are NaN/Inf: empty output"]
        row.update(points_out=len(res.points), notes=notes)
        row["seconds"] = time.perf_counter() - start
    except MsdnetError as err:
        row["error"] = str(err) if err.path else f"{src}: {err}"
    except Exception as err:  # one bad file must not stop the batch
        row["error"] = f"{src}: {type(err).__name__}: {' '.join(str(err).split())[:200]}"
    return row


def _picture(target: Path, radar: Any, dense: Any, artifact: Any, title: str) -> None:
    """The ``--png`` picture of one file: the output over the radar points inside the grid box."""
    from msdnet.runtime.io.pictures import RADAR_COLOUR, Layer, render_bev

    name = "R2LDM" if artifact.kind == "r2ldm" else "MSDNet"
    layers = [
        Layer(dense, "#1f5fbf", f"{name} output", "voxels"),
        Layer(radar, RADAR_COLOUR, "radar in the grid", "radar", of=len(radar)),
    ]
    note = "counts: the points drawn, all inside the grid box (radar: of those read)"
    render_bev(target, layers, artifact.grid, title, note)
