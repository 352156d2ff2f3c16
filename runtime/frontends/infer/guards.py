"""Guards around a ``msdnet-infer`` batch: the output folder, the worker count, killed parents.

- ``check_out``: ``--out`` must not be a file, nor the folder of an input (outputs would land
  among the inputs and the next run would read them as inputs).
- ``prepare_out``: create ``--out``, prove it writable with one temporary file (a read-only file
  system or missing permission is one line naming the folder, before any work), and remove the
  temporary files a killed run left there (``io.atomic.clean_stale_temps``).
- ``clamp_workers``: no more worker processes than CPU cores (with a warning) or files.
- ``check_extras``: the extras the options and inputs need (``--png``: pictures, ``--dataset``:
  metrics, ``.pcd``/``.ply``: formats), each missing one a line before any work.
- ``watch_parent``: a worker process exits as soon as its parent is gone (a SIGKILLed
  ``msdnet-infer`` leaves no worker running).

The model and the options checked against it: ``frontends/model_args`` (shared with
``msdnet-node``).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import click

from msdnet.runtime.errors import MsdnetError, require_extra
from msdnet.runtime.io.atomic import check_writable, write_error

PARENT_POLL_S = 0.2  # how often a worker checks that its parent is alive


def check_extras(png: bool, dataset: bool, fmt: str, files: Sequence[Path] = ()) -> None:
    """One ``MsdnetError`` naming the extra to install when an option or input needs a package that
    a runtime-only install leaves out; nothing is imported."""
    if png:
        require_extra("matplotlib", "--png")
    if dataset:
        require_extra("scipy", "--dataset (scores against the LiDAR)")
        require_extra("pypatchworkpp", "--dataset (ground removal)")
    libs = {"pcd": "pypcd4", "ply": "plyfile"}
    if fmt in libs:
        require_extra(libs[fmt], f"--format {fmt}")
    for suffix in sorted({f.suffix.lower().lstrip(".") for f in files} & set(libs)):
        require_extra(libs[suffix], f".{suffix} inputs")


def check_out(out: Path, inputs: Sequence[Path]) -> None:
    """Refuse an ``--out`` that is an existing non-folder, or the folder of any input."""
    if out.exists() and not out.is_dir():
        raise MsdnetError(out, "--out exists and is not a folder")
    target = out.resolve()
    for item in inputs:
        folder = item if item.is_dir() else item.parent
        if folder.resolve() == target:
            raise MsdnetError(out, f"--out is the folder of input {item}; choose another --out")


def prepare_out(out: Path) -> None:
    """Check ``out`` is writable and clean a killed run's temporaries there
    (``io.atomic.check_writable``, the check every command shares), then create it."""
    check_writable(out, "into")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise write_error(out, err) from None


def usable_cores() -> int:
    """CPU cores this process may run on (affinity-aware)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def clamp_workers(workers: int, n_jobs: int) -> int:
    """``workers`` cut to the CPU cores (warning on stderr) and to the number of jobs."""
    cores = usable_cores()
    if workers > cores:
        click.echo(
            f"warning: --workers {workers} is more than the {cores} CPU cores here; using {cores}",
            err=True,
        )
        workers = cores
    return max(1, min(workers, n_jobs))


def watch_parent(parent_pid: int) -> None:
    """Start a daemon thread that ends this process when ``parent_pid`` is no longer its parent
    (the parent died and the process was re-parented)."""

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(3)
            time.sleep(PARENT_POLL_S)

    threading.Thread(target=watch, name="msdnet-parent-watch", daemon=True).start()
