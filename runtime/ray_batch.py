"""``msdnet-infer INPUTS --out OUT --ray [ADDRESS]``: spread the files over a Ray cluster.

Ray Data (``[ray]`` extra) turns the (input, output) pairs into a dataset of one row per file
(one block per file) and runs ``map_batches`` with a pool of actors: each actor builds ONE
:class:`~msdnet.runtime.pipeline.Pipeline` with ``threads`` intra-op threads (``--threads``,
default 1 under ``--ray``; the actor reserves that many CPUs) and runs the file mode's own
per-file function (``infer_cli._run_one``: read, densify, atomic write), so the bytes equal a
local run at the same thread count and the rows are the ones the local summary counts. The
model's verified bytes travel to the actors with the task, so only the input and output paths
have to be visible to every node (a shared file system), and msdnet must be installed there.

ADDRESS: ``local`` (``--ray`` alone: start a Ray instance on this machine), ``auto`` (the
cluster this machine belongs to, e.g. after ``ray start --head``), ``HOST:6379`` (a head's GCS)
or ``ray://HOST:10001`` (Ray Client). When this process is already connected (``ray.init`` done
by the caller) that connection is used. Ray >= 2.59 starts clusters with token authentication:
a client then needs ``RAY_AUTH_MODE=token`` (the token comes from ``~/.ray/auth_token`` or
``RAY_AUTH_TOKEN``).

A worker that dies is not retried (actor restarts and task retries are off): the run stops, every
file without a result is reported as failed ("no result, the Ray run stopped (ActorDiedError..."),
and the temporary file a killed writer leaves next to its output is removed
(``io.clean_stale_temps``), so OUT holds whole files only (``--skip-existing`` resumes).
"""

from __future__ import annotations

import json
import logging
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io import clean_stale_temps

DEFAULT_THREADS = 1  # intra-op threads per actor when --threads is not given


class _InferActor:
    """One Pipeline per actor; ``__call__`` runs a batch of (src, dst) rows through ``_run_one``."""

    def __init__(self, artifact: Any, provider: str, threads: int, opts: dict[str, Any]) -> None:
        from msdnet.runtime import infer_cli
        from msdnet.runtime.pipeline import Pipeline

        infer_cli._WORKER.update(pipe=Pipeline(artifact, provider=provider, threads=threads), opts=opts)
        self._run = infer_cli._run_one

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        rows = [self._run(str(s), str(d)) for s, d in zip(batch["src"], batch["dst"], strict=True)]
        return {"row": np.array([json.dumps(r) for r in rows])}


def _connect(address: str) -> bool:
    """Connect to Ray unless already connected; -> whether this call connected (and must shut down)."""
    try:
        import ray
    except ImportError:
        raise MsdnetError("--ray", "needs Ray Data: pip install 'msdnet[ray]'") from None
    if ray.is_initialized():
        return False
    try:
        ray.init(
            address=address,  # "local": always a new instance, never a running cluster
            logging_level=logging.ERROR,
            log_to_driver=False,
            include_dashboard=False,
        )
    except Exception as err:  # ConnectionError, ValueError, RuntimeError... from ray.init
        cause = " ".join(str(err).split())[:200]
        hint = "; a cluster with token authentication also needs RAY_AUTH_MODE=token here (and its token)"
        raise MsdnetError("--ray", f"cannot connect to {address!r}: {cause}{hint}") from None
    return True


def run_ray(
    address: str,
    artifact: Any,
    provider: str,
    threads: int | None,
    jobs: Sequence[tuple[str, str]],
    opts: dict[str, Any],
    bar: Any = None,
) -> list[dict[str, Any]]:
    """Run every (src, dst) job on Ray actors; -> rows in job order (as ``infer_cli._run_one``)."""
    started = _connect(address)
    import ray
    import ray.data

    try:
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = False
        ctx.print_on_execution_start = False
        quiet = logging.getLogger("ray.data")
        level = quiet.level
        quiet.setLevel(logging.CRITICAL)  # a dead actor is reported in the summary, not as a traceback
        threads = threads or DEFAULT_THREADS
        cpus = float(ray.cluster_resources().get("CPU", 1.0))
        actors = max(1, min(len(jobs), int(cpus // threads)))
        items = [{"src": s, "dst": d} for s, d in jobs]
        with warnings.catch_warnings():  # max_restarts=0 is how Ray Data turns restarts off
            warnings.filterwarnings("ignore", message=".*ray_remote_args.*deprecated")
            ds = ray.data.from_items(items, override_num_blocks=len(items)).map_batches(
                _InferActor,
                batch_size=1,
                compute=ray.data.ActorPoolStrategy(min_size=1, max_size=actors),
                fn_constructor_args=(artifact, provider, threads, opts),
                num_cpus=threads,
                max_restarts=0,
                max_task_retries=0,
            )
        done: dict[str, dict[str, Any]] = {}
        cause = ""
        try:
            for item in ds.iter_rows():
                row = json.loads(item["row"])
                done[row["file"]] = row
                if bar is not None:
                    bar.update()
        except Exception as err:  # a dead actor, a lost node: report what did not finish
            cause = f"{type(err).__name__}: {(str(err).strip().splitlines() or [''])[0][:160]}"
        finally:
            quiet.setLevel(level)
    finally:
        if started:
            ray.shutdown()
    missing = [(src, dst) for src, dst in jobs if src not in done]
    for folder in {Path(dst).parent for _, dst in missing}:
        clean_stale_temps(folder)  # the temporary file of a killed writer (its process is gone)
    for src, _ in missing:
        done[src] = {"file": src, "points_in": 0, "points_out": 0, "seconds": 0.0}
        done[src]["error"] = f"{src}: no result, the Ray run stopped ({cause or 'no reason given'})"
    return [done[src] for src, _ in jobs]
