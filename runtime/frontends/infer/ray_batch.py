"""``msdnet-infer INPUTS --out OUT --ray [ADDRESS]``: spread the files over a Ray cluster.

Ray Data (``[ray]`` extra) turns the (input, output) pairs into a dataset of one row per file
(one block per file) and runs ``map_batches`` with a pool of actors: each actor builds ONE
:class:`~msdnet.runtime.engine.pipeline.Pipeline` with ``threads`` intra-op threads (``--threads``,
default 1 under ``--ray``; the actor reserves that many CPUs) and runs the file mode's own
per-file function (``worker._run_one``: read, densify, atomic write), so the bytes equal a
local run at the same thread count and the rows are the ones the local summary counts. The
model's verified bytes travel to the actors with the task, so only the input and output paths
have to be visible to every node (a shared file system), and msdnet must be installed there.

ADDRESS: ``local`` (``--ray`` alone: start a Ray instance on this machine), ``auto`` (the
cluster this machine belongs to, e.g. after ``ray start --head``), ``HOST:6379`` (a head's GCS)
or ``ray://HOST:10001`` (Ray Client). When this process is already connected (``ray.init`` done
by the caller) that connection is used. Ray >= 2.59 starts clusters with token authentication:
a client then needs ``RAY_AUTH_MODE=token`` (the token comes from ``~/.ray/auth_token`` or
``RAY_AUTH_TOKEN``).

Staying on the machine: a local instance (``local``) listens on 127.0.0.1 only (Ray otherwise
rewrites a loopback address to the machine's interface address), with the dashboard off, usage
stats off (``RAY_USAGE_STATS_ENABLED=0`` unless set) and no cloud-metadata probe: Ray's head
processes see a private ``HOME`` holding a ``ray_bootstrap_config.yaml`` that names the local
provider (without one, Ray's usage module asks 169.254.169.254 and metadata.google.internal
which cloud it runs on); the instance's workers inherit that ``HOME`` too (a job-level
``runtime_env`` restoring the real one made the workers crash at start with Ray 2.60), and the
folder is removed when the instance shuts down. Ray >= 2.59 turns token authentication on for a
new local instance and caches the token in this process: a token file written into the private
``HOME`` would be gone for the next instance, whose GCS server then aborts ("Token authentication
is enabled but Ray couldn't find an authentication token") and Ray waits out its GCS port
timeout. So every local instance of a process gets the same random token through
``RAY_AUTH_TOKEN`` in its head processes' environment, unless the user set up Ray's
authentication (``RAY_AUTH_MODE``, ``RAY_AUTH_TOKEN`` or ``RAY_AUTH_TOKEN_PATH``) already. A loopback ADDRESS
(``127.0.0.1:6379``) is kept as given. An ADDRESS where nothing answers fails after ``timeout``
seconds (``--ray-timeout``, default 30) in one line naming it, instead of Ray's endless retries.

A worker that dies is not retried (actor restarts and task retries are off): the run stops, every
file without a result is reported as failed ("no result, the Ray run stopped (ActorDiedError..."),
and the temporary file a killed writer leaves next to its output is removed
(``io.atomic.clean_stale_temps``), so OUT holds whole files only (``--skip-existing`` resumes).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import secrets
import shutil
import socket
import tempfile
import time
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.densify import DensifyOptions
from msdnet.runtime.io.atomic import clean_stale_temps

DEFAULT_THREADS = 1  # intra-op threads per actor when --threads is not given
DEFAULT_TIMEOUT_S = 30.0  # --ray-timeout: how long an ADDRESS may take to answer
LOOPBACK = "127.0.0.1"
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
CLIENT_PORT = 10001  # Ray Client's default port (ray://HOST)
BOOTSTRAP_CONFIG = "ray_bootstrap_config.yaml"  # read from ~ by Ray's usage module (dashboard)
LOCAL_PROVIDER = "# msdnet: a local Ray instance (no cloud to ask about)\nprovider:\n  type: local\n"
AUTH_VARS = ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")  # the user's own Ray auth setup
_LOCAL_TOKEN: list[str] = []  # this process's token for its local instances (made once)


class _InferActor:
    """One Pipeline per actor; ``__call__`` runs a batch of (src, dst) rows through ``_run_one``."""

    def __init__(self, artifact: Any, provider: str, threads: int, options: DensifyOptions) -> None:
        from msdnet.runtime.engine.pipeline import Pipeline
        from msdnet.runtime.frontends.infer import worker

        worker.WORKER.update(pipe=Pipeline(artifact, provider=provider, threads=threads), options=options)
        self._run = worker._run_one

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        rows = [self._run(str(s), str(d)) for s, d in zip(batch["src"], batch["dst"], strict=True)]
        return {"row": np.array([json.dumps(r) for r in rows])}


def _ray() -> Any:
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # before Ray starts anything
    # a slow start of the GCS server gets 120 s instead of Ray's 30 (a GCS server that aborts,
    # as one without its auth token did, waits all of it: see local_instance)
    os.environ.setdefault("RAY_gcs_server_port_wait_time_s", "120")
    try:
        import ray
    except ImportError:
        raise MsdnetError("--ray", "needs Ray Data: pip install 'msdnet[ray]'") from None
    return ray


@contextlib.contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    """Set environment variables for the block, then restore each one (or remove it again)."""
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def _loopback_kept(ray: Any) -> Iterator[None]:
    """While connecting: Ray keeps 127.0.0.1 as 127.0.0.1 (its "no cluster" setting, which makes
    this node's address the loopback one) in this process and in the processes it starts."""
    constants = ray._private.ray_constants
    var = constants.ENABLE_RAY_CLUSTERS_ENV_VAR  # RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER
    flag = constants.ENABLE_RAY_CLUSTER
    constants.ENABLE_RAY_CLUSTER = False
    try:
        with _environment({var: "0"}):
            yield
    finally:
        constants.ENABLE_RAY_CLUSTER = flag


def _init_options() -> dict[str, Any]:
    return {"logging_level": logging.ERROR, "log_to_driver": False, "include_dashboard": False}


@contextlib.contextmanager
def local_instance(num_cpus: int | None = None) -> Iterator[None]:
    """Start a Ray instance on this machine that stays on it (module docstring), shut it down on exit."""
    ray = _ray()
    home = Path(tempfile.mkdtemp(prefix="msdnet-ray-home-"))
    head_env = {"HOME": str(home)}  # what the head processes started now inherit
    if not _LOCAL_TOKEN and not any(v in os.environ for v in AUTH_VARS):  # decided once: Ray
        _LOCAL_TOKEN.append(secrets.token_hex(32))  # itself sets RAY_AUTH_MODE=token at its first init
    if _LOCAL_TOKEN:
        head_env["RAY_AUTH_TOKEN"] = _LOCAL_TOKEN[0]
    try:
        (home / BOOTSTRAP_CONFIG).write_text(LOCAL_PROVIDER)
        with _environment(head_env), _loopback_kept(ray):
            ray.init(
                address="local",
                _node_ip_address=LOOPBACK,
                num_cpus=num_cpus,
                **_init_options(),
            )
        yield
    except MsdnetError:
        raise
    except Exception as err:
        if ray.is_initialized():
            raise
        raise MsdnetError("--ray", f"cannot start a local Ray instance: {_cause(err)}") from None
    finally:
        ray.shutdown()
        shutil.rmtree(home, ignore_errors=True)


def _cause(err: BaseException) -> str:
    return " ".join(str(err).split())[:200] or type(err).__name__


def _host_port(ray: Any, address: str) -> tuple[str, int] | None:
    """The (host, port) ``address`` makes Ray connect to first; None when it cannot tell."""
    addr = address
    if addr == "auto":
        try:
            addr = ray._private.services.get_ray_address_from_environment("auto", None)
        except Exception as err:  # no running instance found
            raise MsdnetError("--ray", f"no Ray cluster found for 'auto': {_cause(err)}") from None
    default = CLIENT_PORT if addr.startswith("ray://") else None
    host, _, port = addr.removeprefix("ray://").rpartition(":")
    if not host:
        host, port = port, str(default or "")
    host = host.strip("[]")
    return (host, int(port)) if host and port.isdigit() else None


def _wait_for(address: str, host: str, port: int, timeout: float) -> None:
    """Return once something accepts a TCP connection at (host, port); MsdnetError after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        try:
            with socket.create_connection((host, port), timeout=max(0.1, min(2.0, left))):
                return
        except OSError as err:
            if time.monotonic() + 0.5 >= deadline:
                where = address if address == f"{host}:{port}" else f"{address} ({host}:{port})"
                raise MsdnetError(
                    "--ray",
                    f"nothing answers at {where} within {timeout:g} s ({err.strerror or _cause(err)}); "
                    "start the cluster (ray start --head) or check the address (--ray-timeout: wait longer)",
                ) from None
        time.sleep(0.5)


@contextlib.contextmanager
def _connected(address: str, timeout: float) -> Iterator[None]:
    """Use this process's Ray connection, a new local instance, or the cluster at ``address``."""
    ray = _ray()
    if ray.is_initialized():
        yield
        return
    if address == "local":  # always a new instance, never a running cluster
        with local_instance():
            yield
        return
    target = _host_port(ray, address)
    if target is not None:
        _wait_for(address, *target, timeout)
    loopback = target is not None and target[0] in LOOPBACK_HOSTS
    try:
        with _loopback_kept(ray) if loopback else contextlib.nullcontext():
            ray.init(
                address=address, **({"_node_ip_address": LOOPBACK} if loopback else {}), **_init_options()
            )
    except Exception as err:  # ConnectionError, ValueError, RuntimeError... from ray.init
        hint = "; a cluster with token authentication also needs RAY_AUTH_MODE=token here (and its token)"
        raise MsdnetError("--ray", f"cannot connect to {address!r}: {_cause(err)}{hint}") from None
    try:
        yield
    finally:
        ray.shutdown()


def run_ray(
    address: str,
    artifact: Any,
    provider: str,
    threads: int | None,
    jobs: Sequence[tuple[str, str]],
    options: DensifyOptions,
    bar: Any = None,
    timeout: float = DEFAULT_TIMEOUT_S,
) -> list[dict[str, Any]]:
    """Run every (src, dst) job on Ray actors; -> rows in job order (as ``worker._run_one``).
    ``timeout``: seconds ``address`` may take to answer (not used for ``local``)."""
    with _connected(address, timeout):
        return _run(artifact, provider, threads, jobs, options, bar)


def _run(
    artifact: Any,
    provider: str,
    threads: int | None,
    jobs: Sequence[tuple[str, str]],
    options: DensifyOptions,
    bar: Any,
) -> list[dict[str, Any]]:
    import ray
    import ray.data

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
            fn_constructor_args=(artifact, provider, threads, options),
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
    missing = [(src, dst) for src, dst in jobs if src not in done]
    for folder in {Path(dst).parent for _, dst in missing}:
        clean_stale_temps(folder)  # the temporary file of a killed writer (its process is gone)
    for src, _ in missing:
        done[src] = {"file": src, "points_in": 0, "points_out": 0, "seconds": 0.0}
        done[src]["error"] = f"{src}: no result, the Ray run stopped ({cause or 'no reason given'})"
    return [done[src] for src, _ in jobs]
