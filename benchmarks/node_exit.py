"""``msdnet-bench node-exit``: msdnet-node stopped by a signal in every state of a first run.

    msdnet-bench node-exit --runs 10 --out docs/results/node-exit

Each run starts one ``msdnet-node`` at the default provider (``auto``) with a fresh, empty
engine cache (``XDG_CACHE_HOME``) and a fresh ``HOME``, so ``auto`` measures the engines in that
process, as on a vehicle's first start. The ``--runs`` runs send the signal at delays spread
evenly from ``--first-s`` to ``--last-s`` after the start (the model loading, the engines'
measurement, the warm-up, joining DDS, and serving with no scan); the ``--load-runs`` runs wait
for the ready line, start a publisher of synthetic scans at ``--hz`` and send the signal
``--load-s`` after the node's first scan, scans in flight. Every participant uses the
loopback-only Cyclone configuration.

A run passes when the node exits with status 0 within ``EXIT_LIMIT_S`` of the signal, its last
stdout line is the stats line, the ``--stats-json`` file is whole JSON and stderr holds no
traceback. Results: ``OUT/results.json`` and ``OUT/results.md`` (each run: the signal, its
delay, the state the node was in, the exit status and time, the stats it wrote).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import click
import numpy as np

from msdnet.benchmarks.machine import machine_info
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import checks_outputs

EXIT_LIMIT_S = 5.0  # signal -> exit, at most (the node's own bound is GRACE_S while serving)
DOMAIN_BASE = 150  # domain ids of the runs: DOMAIN_BASE + run (apart from the tests')
SIGNALS = {"SIGTERM": signal.SIGTERM, "SIGINT": signal.SIGINT}
SCANS = 3  # synthetic scans the load runs' publisher sends in turn
SCAN_POINTS = 600  # points per synthetic scan


def _scans(model: Path, folder: Path) -> list[Path]:
    """A few synthetic scans in ``model``'s columns, uniform over its grid, as PCD files."""
    from msdnet.runtime.engine.pointcloud import PointCloud
    from msdnet.runtime.io.files import write_cloud
    from msdnet.runtime.model.artifact import load_artifact

    artifact = load_artifact(model)
    rng = np.random.default_rng(0)
    lo = np.asarray(artifact.grid.point_range[:3], np.float32)
    hi = np.asarray(artifact.grid.point_range[3:], np.float32)
    files = []
    for i in range(SCANS):
        pts = np.zeros((SCAN_POINTS, len(artifact.inputs.columns)), np.float32)
        pts[:, :3] = lo + (hi - lo) * rng.random((SCAN_POINTS, 3), dtype=np.float32)
        files.append(write_cloud(folder / f"scan{i}.pcd", PointCloud(pts, tuple(artifact.inputs.columns))))
    return files


class _Lines:
    """A process's stdout lines, each with the monotonic time it arrived, read in a thread."""

    def __init__(self, stream: Any) -> None:
        self.lines: list[tuple[float, str]] = []
        self.ready = threading.Event()  # the node serves
        self.flowing = threading.Event()  # it has handled a scan (a stats line after the ready line)
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream: Any) -> None:
        for line in stream:
            self.lines.append((time.monotonic(), line.rstrip("\n")))
            if "msdnet-node: serving" in line:
                self.ready.set()
            elif self.ready.is_set() and line.startswith("msdnet-node: received"):
                self.flowing.set()

    def join(self) -> None:
        self._thread.join(timeout=5.0)


def start_and_stop(
    index: int,
    work: Path,
    model: Path | None,
    signum: int,
    delay_s: float,
    load_hz: float | None,
    domain: int | None = None,
) -> dict[str, Any]:
    """One start / signal / exit (module docstring) in ``work`` on DDS ``domain`` (default
    ``DOMAIN_BASE + index``); -> its record."""
    from msdnet.runtime.frontends.live.dds import loopback_env

    folder = work / f"run-{index:02d}"
    (folder / "home").mkdir(parents=True, exist_ok=True)
    env = loopback_env(folder)
    env["HOME"], env["XDG_CACHE_HOME"] = str(folder / "home"), str(folder / "xdg")
    stats_path = folder / "stats.json"
    domain = DOMAIN_BASE + index if domain is None else domain
    cmd = [sys.executable, "-m", "msdnet.runtime.frontends.live.cli", "--domain-id", str(domain)]
    cmd += ["--stats-json", str(stats_path)] + ([] if model is None else ["--model", str(model)])
    cmd += [] if load_hz is None else ["--stats-every", "1"]  # a line per scan: the scans flow
    publisher = None
    start = time.monotonic()
    err_path = folder / "stderr.txt"
    with open(err_path, "w", encoding="utf-8") as err_file:  # stdout is read line by line below
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=err_file, text=True)
    lines = _Lines(proc.stdout)
    if load_hz is None:
        time.sleep(max(0.0, start + delay_s - time.monotonic()))
    else:  # scans in flight: wait for the node to serve, publish, then the signal
        lines.ready.wait(timeout=120.0)
        files = _scans(model or _bundled(), folder)
        pub = [sys.executable, "-m", "msdnet.runtime.frontends.live.publish", *map(str, files)]
        pub += ["--domain-id", str(domain), "--hz", f"{load_hz:g}", "--count", str(int(load_hz * 600))]
        publisher = subprocess.Popen(pub, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        lines.flowing.wait(timeout=120.0)  # the publisher's start-up is not the node's load
        time.sleep(delay_s)
    sent = time.monotonic()
    proc.send_signal(signum)
    try:
        proc.wait(timeout=60.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    exit_s = time.monotonic() - sent
    lines.join()
    err = err_path.read_text(encoding="utf-8", errors="replace")
    if publisher is not None:
        publisher.kill()
        publisher.wait()
    try:
        stats = json.loads(stats_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        stats = None
    last = lines.lines[-1][1] if lines.lines else ""
    record = {
        "run": index,
        "signal": signal.Signals(signum).name,
        "delay_s": round(delay_s, 3),
        "after": "the first scan" if load_hz is not None else "the start",
        "state": "?" if stats is None else stats.get("stopped_while", "?"),
        "scans_in_flight": load_hz is not None,
        "measured_engines": "provider auto: measured" in err,
        "returncode": proc.returncode,
        "exit_s": round(exit_s, 3),
        "stats_line": last.startswith("msdnet-node: received"),
        "stats_file": stats is not None,
        "received": None if stats is None else stats.get("received"),
        "published": None if stats is None else stats.get("published"),
        "traceback": "Traceback" in err,
    }
    record["ok"] = bool(
        proc.returncode == 0
        and exit_s <= EXIT_LIMIT_S
        and record["stats_line"]
        and record["stats_file"]
        and not record["traceback"]
    )
    if not record["ok"]:
        record["stderr_tail"] = err[-600:]
    return record


def _bundled() -> Path:
    from msdnet.runtime.frontends.model_args import BUNDLED_MODEL

    return BUNDLED_MODEL


def markdown(doc: dict[str, Any]) -> str:
    """results.md: the tally, then one row per run."""
    m = doc["machine"]
    lines = [
        "# msdnet-node stopped by a signal on a first run",
        "",
        f"{doc['passed']} of {len(doc['runs'])} runs exited 0 within {EXIT_LIMIT_S:g} s with the stats "
        f"line and a whole stats JSON; each started with an empty engine cache and a fresh HOME, "
        f"provider {doc['provider']}, model `{doc['model']}`.",
        "",
        f"Machine: {m.get('cpu', '?')}, {m.get('logical_cores', '?')} logical cores, load average "
        f"{doc['load_before']:.2f} before and {doc['load_after']:.2f} after. {doc['note']}",
        "",
        "| run | signal | after | delay s | state | engine picks measured | exit | exit s | stats line "
        "| stats file | received / published |",
        "|---:|---|---|---:|---|---|---:|---:|---|---|---|",
    ]
    for c in doc["runs"]:
        got = "" if c["received"] is None else f"{c['received']} / {c['published']}"
        lines.append(
            f"| {c['run']} | {c['signal']} | {c['after']} | {c['delay_s']:g} | {c['state']} | "
            f"{'yes' if c['measured_engines'] else 'no'} | {c['returncode']} | {c['exit_s']:.2f} | "
            f"{'yes' if c['stats_line'] else 'NO'} | {'yes' if c['stats_file'] else 'NO'} | {got} |"
        )
    return "\n".join(lines) + "\n"


@click.command("node-exit", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--runs", type=click.IntRange(min=0, max=200), default=10, show_default=True)
@click.option("--load-runs", type=click.IntRange(min=0, max=200), default=2, show_default=True)
@click.option(
    "--signal", "signal_name", type=click.Choice(sorted(SIGNALS)), default="SIGTERM", show_default=True
)
@click.option("--first-s", type=click.FloatRange(min=0.0, max=120.0), default=0.5, show_default=True)
@click.option("--last-s", type=click.FloatRange(min=0.0, max=120.0), default=8.0, show_default=True)
@click.option("--hz", type=click.FloatRange(min=0.5, max=100.0), default=20.0, show_default=True)
@click.option("--load-s", type=click.FloatRange(min=0.0, max=60.0), default=2.0, show_default=True)
@click.option("--model", type=click.Path(path_type=Path), help="msdnet-export folder [bundled sim-lite].")
@click.option("--note", default="", help="A line for the page (e.g. what else loads the machine).")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Folder for results.*")
@one_line_errors
@checks_outputs(out="into")  # before any work
def node_exit_command(
    runs: int,
    load_runs: int,
    signal_name: str,
    first_s: float,
    last_s: float,
    hz: float,
    load_s: float,
    model: Path | None,
    note: str,
    out: Path,
) -> None:
    """Start msdnet-node with an empty engine cache and stop it by a signal, --runs times across
    its start-up and --load-runs times with scans in flight: every exit must be 0 with its stats."""
    import tempfile

    from msdnet.benchmarks.args import check_model_folder
    from msdnet.benchmarks.stages import write_markdown_and_json
    from msdnet.runtime.frontends.live.dds import cyclonedds

    cyclonedds()
    if last_s < first_s:
        raise MsdnetError("--last-s", f"must be >= --first-s ({first_s:g}), got {last_s:g}")
    if runs + load_runs == 0:
        raise MsdnetError("--runs", "nothing to do (--runs and --load-runs are both 0)")
    if model is not None:
        check_model_folder("--model", model)
    signum = SIGNALS[signal_name]
    delays = list(np.linspace(first_s, last_s, runs)) if runs > 1 else [first_s] * runs
    records = []
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="msdnet-node-exit-") as tmp:
        plan = [(d, None) for d in delays] + [(load_s, hz)] * load_runs
        for i, (delay, rate) in enumerate(plan):
            rec = start_and_stop(i, Path(tmp), model, signum, float(delay), rate)
            records.append(rec)
            verdict = "ok" if rec["ok"] else "FAILED"
            click.echo(
                f"run {i}: {rec['signal']} {rec['delay_s']:g} s after {rec['after']} ({rec['state']}) -> "
                f"exit {rec['returncode']} in {rec['exit_s']:.2f} s, stats file "
                f"{'yes' if rec['stats_file'] else 'no'}: {verdict}",
                err=True,
            )
    doc = {
        "provider": "auto",
        "model": str(model or "bundled sim-lite"),
        "runs": records,
        "passed": sum(r["ok"] for r in records),
        "load_before": load_before,
        "load_after": os.getloadavg()[0],
        "note": note or "Nothing noted about the machine's load.",
        "machine": asdict(machine_info(sgemm=False)),
    }
    write_markdown_and_json(doc, markdown(doc), out, "results")
    click.echo(f"{doc['passed']} of {len(records)} runs passed; wrote {out}/results.json and results.md")
    if doc["passed"] != len(records):
        raise SystemExit(1)
