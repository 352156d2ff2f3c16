"""``msdnet-bench live``: msdnet-node end to end on loopback: latency, drops, max rate, a storm.

Processes: a publisher (``runtime/frontends/live/publish``) sends the VoD example radar scans in turn
as ``/radar/points`` at a fixed rate (PointCloud2, or RadarScan with ``--input radar_scan``: x y z
in polar form, the compensated radial velocity as doppler_velocity); one ``msdnet-node`` (the
model, ``--threads``) densifies them;
this process collects ``/radar/points/dense`` and matches replies to sends by header stamp.
End-to-end latency = reply received - scan sent (both CLOCK_MONOTONIC); drops = scans sent
without a reply (the node counts those it replaced: latest-message-wins). Every participant uses
the loopback-only CYCLONEDDS_URI (``runtime/frontends/live/dds.loopback_env``) and a domain id of its own.

Runs: 10 and 20 Hz for ``messages`` scans each; the highest rate held without a drop (a ladder
down from 1 / the node's median service time, ``ladder_messages`` each); the storm:
``storm_hz`` for ``storm_s`` seconds — every latency within one scan's time plus one (2 x the
largest service time, plus ``SLACK_S``), drops counted, resident memory flat (last vs first
quarter after a warm-up, < 5 %), then a second publisher process (the first one has exited) is
served, and SIGTERM ends the node within a second. Results: ``OUT/live.json`` and ``OUT/live.md``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import click
import numpy as np

from msdnet.benchmarks.machine import machine_info, shown_path
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.frontends.model_args import resolve_model

WARMUP_REPLIES = 10  # the storm's memory baseline starts once this many replies are out
MEMORY_FLAT_PCT = 5.0  # "memory flat": growth over the storm below this share (as msdnet-bench soak)
SLACK_S = 0.1  # transport and scheduling allowance on the storm's latency bound
TOPIC = "/radar/points"
INPUT_TYPES = {"pointcloud2": "sensor_msgs/msg/PointCloud2", "radar_scan": "radar_msgs/msg/RadarScan"}


class NodeRun:
    """One msdnet-node process and a /dense collector in this process."""

    def __init__(
        self,
        env: dict[str, str],
        domain: int,
        model: Path,
        threads: int | None,
        work: Path,
        input_type: str = "pointcloud2",
    ) -> None:
        from msdnet.runtime.frontends.live.publish import DenseCollector

        self.env, self.domain, self.stats_path = env, domain, work / f"node-{domain}.json"
        cmd = [sys.executable, "-m", "msdnet.runtime.frontends.live.cli", "--domain-id", str(domain)]
        cmd += ["--model", str(model), "--stats-json", str(self.stats_path)]
        cmd += [] if threads is None else ["--threads", str(threads)]
        cmd += ["--input-type", input_type]
        self.input_type = input_type
        self.proc = subprocess.Popen(
            cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        line = self.proc.stdout.readline()
        if "serving" not in line:
            raise MsdnetError("msdnet-node", f"did not start: {line.strip() or 'no output'}")
        self.collector = DenseCollector(TOPIC, domain, keep_points=False)
        self.collector.wait_matched()
        self.rss: list[tuple[float, float, int]] = []  # (monotonic s, MiB, replies so far)

    def publish(
        self, files: list[Path], hz: float, count: int, start_ns: int, work: Path
    ) -> dict[int, float]:
        """Run one publisher process; -> {stamp_ns: send time}."""
        log = work / f"sent-{self.domain}-{start_ns}.json"
        cmd = [
            sys.executable,
            "-m",
            "msdnet.runtime.frontends.live.publish",
            *map(str, files),
            "--domain-id",
            str(self.domain),
        ]
        cmd += ["--hz", str(hz), "--count", str(count), "--start-ns", str(start_ns), "--log", str(log)]
        if self.input_type == "radar_scan":  # the same scans as RadarScan (VoD: the compensated v_r)
            cmd += ["--radar-scan", "--velocity", "v_r_compensated"]
        proc = subprocess.Popen(
            cmd, env=self.env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        while proc.poll() is None:
            self.rss.append((time.monotonic(), _rss_mib(self.proc.pid), len(self.collector.received)))
            time.sleep(0.25)
        if proc.returncode:
            raise MsdnetError("publisher", proc.stderr.read().strip().splitlines()[-1])
        return {int(s): float(t) for s, t in json.loads(log.read_text())["sent"]}

    def stop(self) -> tuple[float, dict[str, Any]]:
        """SIGTERM -> (seconds to exit, the node's stats)."""
        self.collector.close()
        start = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(timeout=30)
        return time.monotonic() - start, json.loads(self.stats_path.read_text())


def _rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _pct(values: list[float]) -> dict[str, float | None]:
    a = np.asarray(values, dtype=np.float64) * 1e3
    if not a.size:
        return {"p50": None, "p90": None, "p99": None, "max": None}
    return {
        **{f"p{q}": round(float(np.percentile(a, q)), 1) for q in (50, 90, 99)},
        "max": round(float(a.max()), 1),
    }


def _replies(run: NodeRun, sent: dict[int, float], settle: float) -> list[float]:
    """End-to-end latencies (s) of the replies to ``sent``, after ``settle`` seconds for the last."""
    time.sleep(settle)
    got = {s: t for s, t, _ in list(run.collector.received) if s in sent}
    return [got[s] - sent[s] for s in got]


def _node(ctx: dict[str, Any]) -> NodeRun:
    """A new node on the next domain, as ``ctx`` sets it up."""
    return NodeRun(
        ctx["env"],
        ctx["next_domain"](),
        ctx["model"],
        ctx["threads"],
        ctx["work"],
        ctx.get("input", "pointcloud2"),
    )


def rate_run(ctx: dict[str, Any], hz: float, count: int, start_ns: int) -> dict[str, Any]:
    """One node, one publisher at ``hz`` for ``count`` scans -> latency percentiles and drops."""
    run = _node(ctx)
    try:
        sent = run.publish(ctx["files"], hz, count, start_ns, ctx["work"])
        lat = _replies(run, sent, settle=2.0)
    finally:
        exit_s, stats = run.stop()
    return {
        "hz": hz,
        "sent": len(sent),
        "replies": len(lat),
        "drops": len(sent) - len(lat),
        "node_dropped": stats["dropped"],
        "end_to_end_ms": _pct(lat),
        "node_receive_to_publish_ms": {k: _round(v) for k, v in stats["latency_ms"].items() if k != "count"},
        "node_service_ms": {k: _round(v) for k, v in stats["service_ms"].items()},
        "sigterm_exit_s": round(exit_s, 3),
        "engines": stats.get("engines"),
    }


def _round(v: float | None) -> float | None:
    return None if v is None else round(v, 1)


def storm_run(ctx: dict[str, Any], hz: float, seconds: float, start_ns: int) -> dict[str, Any]:
    """The storm (module docstring) on one node; -> figures and the pass/fail of each check."""
    run = _node(ctx)
    try:
        sent = run.publish(ctx["files"], hz, round(hz * seconds), start_ns, ctx["work"])
        rss = list(run.rss)  # resident memory over the storm (0.25 s apart)
        lat = _replies(run, sent, settle=2.0)
        before = len(run.collector.received)
        again = run.publish(ctx["files"], 10.0, 20, start_ns + 10**12, ctx["work"])  # a new publisher
        served_again = len(_replies(run, again, settle=2.0))
    finally:
        exit_s, stats = run.stop()
    service_max = (stats["service_ms"]["max"] or 0.0) / 1e3
    bound = 2 * service_max + SLACK_S
    warm = [m for _, m, n in rss if n >= WARMUP_REPLIES] or [m for _, m, _ in rss]  # after warm-up
    quarter = max(len(warm) // 4, 1)
    base = float(np.median(warm[:quarter])) if warm else float("nan")
    growth = float(np.median(warm[-quarter:])) - base if warm else float("nan")
    return {
        "hz": hz,
        "seconds": seconds,
        "sent": len(sent),
        "replies": len(lat),
        "drops": len(sent) - len(lat),
        "node_dropped": stats["dropped"],
        "engines": stats.get("engines"),
        "end_to_end_ms": _pct(lat),
        "bound_ms": round(bound * 1e3, 1),
        "latency_bounded": bool(lat) and max(lat) <= bound,
        "rss_mib_after_warmup": round(base, 1),
        "rss_growth_mib": round(growth, 1),
        "rss_growth_pct": round(100 * growth / base, 2) if warm else None,
        "memory_flat": bool(growth < MEMORY_FLAT_PCT / 100 * base),
        "rss_mib_per_second": [round(m, 1) for _, m, _ in rss[::4]],
        "replies_before_restart": before,
        "restarted_publisher_served": served_again,
        "sigterm_exit_s": round(exit_s, 3),
        "sigterm_within_1s": exit_s < 1.0,
    }


def max_rate(
    ctx: dict[str, Any], service_ms: float, count: int, start_ns: int, tries: int = 5
) -> dict[str, Any]:
    """Highest rate (of a ladder down from 1 / the median service time, x 0.8 per step) with no
    drop over ``count`` scans."""
    hz = max(round(1e3 / max(service_ms, 1.0), 1), 0.5)
    ladder = []
    for _ in range(tries):
        res = rate_run(ctx, hz, count, start_ns)
        ladder.append({"hz": hz, "drops": res["drops"], "end_to_end_p99_ms": res["end_to_end_ms"]["p99"]})
        if res["drops"] == 0:
            return {"max_hz_without_drops": hz, "ladder": ladder}
        hz = round(hz * 0.8, 1)
        start_ns += 10**12
    return {"max_hz_without_drops": None, "ladder": ladder}


def engines_text(engines: dict[str, Any] | None) -> str:
    """``provider auto: encoder.onnx openvino, ...; head coarse-to-fine`` (or the provider alone)."""
    if not engines:
        return "not recorded"
    graphs = ", ".join(f"{f} {e}" for f, e in engines.get("graphs", {}).items())
    text = f"provider {engines['provider']}" + (f": {graphs}" if graphs else "")
    return text + (f"; head {engines['head']}" if engines.get("head") else "")


def markdown(doc: dict[str, Any]) -> str:
    """The results page."""
    lines = [
        "# msdnet-bench live: msdnet-node end to end on loopback",
        "",
        f"Model `{doc['model']}`, threads {doc['threads'] or 'default'}, input "
        f"{INPUT_TYPES[doc.get('input', 'pointcloud2')]}; {doc['note']}.",
        f"Machine: {doc['machine'].get('cpu', '?')}, load average at the start {doc['load_average']}.",
        f"Engines: {engines_text(doc.get('engines'))}.",
        "",
        "End-to-end latency = reply received - scan sent (publisher and subscriber processes on loopback);",
        "node latency = receive -> publish inside msdnet-node; service = one scan's own time (no wait).",
        "",
        "| rate | sent | replies | drops | end-to-end p50 / p90 / p99 / max ms | node p50 / p99 | service |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in doc["rates"]:
        e, n, srv = r["end_to_end_ms"], r["node_receive_to_publish_ms"], r["node_service_ms"]["p50"]
        e_text = f"{e['p50']} / {e['p90']} / {e['p99']} / {e['max']}"
        lines.append(
            f"| {r['hz']:g} Hz | {r['sent']} | {r['replies']} | {r['drops']} | {e_text} |"
            f" {n['p50']} / {n['p99']} | {srv} |"
        )
    m = doc["max_rate"]
    ladder = ", ".join(f"{x['hz']:g} Hz: {x['drops']} drops" for x in m["ladder"])
    lines += ["", f"Highest rate held without drops: **{m['max_hz_without_drops']} Hz** ({ladder}).", ""]
    s = doc["storm"]
    e = s["end_to_end_ms"]
    held = "held" if s["latency_bounded"] else "NOT held"
    flat = "flat" if s["memory_flat"] else "NOT flat"
    within = "within" if s["sigterm_within_1s"] else "NOT within"
    lines += [
        f"## Storm: {s['hz']:g} Hz for {s['seconds']:g} s",
        "",
        f"- sent {s['sent']}, replies {s['replies']}, drops {s['drops']} (replaced while one ran)",
        f"- end-to-end p50 / p90 / p99 / max {e['p50']} / {e['p90']} / {e['p99']} / {e['max']} ms;"
        f" bound (one scan's time plus one, + {SLACK_S * 1e3:g} ms) {s['bound_ms']} ms: {held}",
        f"- resident memory {s['rss_mib_after_warmup']} MiB once {WARMUP_REPLIES} replies were out (first"
        f" quarter after that), {s['rss_growth_mib']} MiB ({s['rss_growth_pct']} %) more over the last"
        f" quarter: {flat} (goal < {MEMORY_FLAT_PCT:g} %)",
        f"- a second publisher after the first exited, 20 scans at 10 Hz: {s['restarted_publisher_served']}"
        " served (the rest replaced)",
        f"- SIGTERM -> exit {s['sigterm_exit_s']} s ({within} 1 s)",
        "",
    ]
    return "\n".join(lines)


def live_bench(
    model: Path,
    files: list[Path],
    threads: int | None,
    messages: int,
    ladder_messages: int,
    storm_hz: float,
    storm_s: float,
    rates: tuple[float, ...] = (10.0, 20.0),
    input_type: str = "pointcloud2",
) -> dict[str, Any]:
    """Every run of the module docstring; -> the results document."""
    from msdnet.runtime.frontends.live.dds import loopback_env

    base = 20 + os.getpid() % 150  # this run's domain ids: base, base + 1, ... (<= 232)
    counter = iter(range(base, 233))
    with tempfile.TemporaryDirectory(prefix="msdnet-live-") as tmp:
        work = Path(tmp)
        env = loopback_env(work)
        os.environ["CYCLONEDDS_URI"] = env["CYCLONEDDS_URI"]  # this process's collector
        ctx = {
            "env": env,
            "model": model,
            "threads": threads,
            "files": files,
            "work": work,
            "next_domain": lambda: next(counter),
            "input": input_type,
        }
        start = 1_700_000_000 * 10**9
        doc: dict[str, Any] = {
            "model": shown_path(model),
            "threads": threads,
            "input": input_type,
            "load_average": [round(x, 2) for x in os.getloadavg()],
        }
        doc["rates"] = [rate_run(ctx, hz, messages, start + i * 10**12) for i, hz in enumerate(rates)]
        p50 = min(r["node_service_ms"]["p50"] or 1.0 for r in doc["rates"])
        doc["max_rate"] = max_rate(ctx, p50, ladder_messages, start + 10 * 10**12)
        doc["storm"] = storm_run(ctx, storm_hz, storm_s, start + 50 * 10**12)
    doc["engines"] = doc["rates"][0].get("engines")  # the node's provider and its picks
    doc["machine"] = asdict(machine_info(sgemm=False))
    return doc


@click.command("live", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--model", type=click.Path(path_type=Path), help="msdnet-export folder [bundled sim-lite].")
@click.option(
    "--data",
    type=click.Path(path_type=Path),
    default=Path("../shared/data/vod_example"),
    show_default=True,
    help="VoD folder whose radar scans are sent.",
)
@click.option("--threads", type=click.IntRange(min=1), help="Node intra-op threads.")
@click.option(
    "--messages", type=click.IntRange(min=1), default=300, show_default=True, help="Scans per rate."
)
@click.option("--ladder-messages", type=click.IntRange(min=1), default=100, show_default=True)
@click.option("--storm-hz", type=float, default=40.0, show_default=True)
@click.option("--storm-s", type=float, default=30.0, show_default=True)
@click.option(
    "--input",
    "input_type",
    type=click.Choice(sorted(INPUT_TYPES)),
    default="pointcloud2",
    show_default=True,
    help="Message type the scans are sent as (radar_scan: results as live-radar_scan.*).",
)
@click.option("--note", default="", help="A line for the page (e.g. what else loads the machine).")
@click.option("--out", type=click.Path(path_type=Path), default=Path("docs/results/live"), show_default=True)
@one_line_errors
def live_command(
    model: Path | None,
    data: Path,
    threads: int | None,
    messages: int,
    ladder_messages: int,
    storm_hz: float,
    storm_s: float,
    input_type: str,
    note: str,
    out: Path,
) -> None:
    """msdnet-node end to end on loopback: latency, drops, max rate, storm."""
    from msdnet.benchmarks.stages import write_markdown_and_json
    from msdnet.runtime.frontends.live.dds import cyclonedds
    from msdnet.runtime.io.atomic import check_writable

    cyclonedds()
    from msdnet.benchmarks.args import check_model_folder
    from msdnet.runtime.engine.pointcloud import canonical_column
    from msdnet.runtime.io.files import read_cloud

    columns = check_model_folder("--model", resolve_model(model)).inputs.columns
    files = sorted((data / "radar" / "training" / "velodyne").glob("*.bin"))
    if not files:
        raise MsdnetError(data, "no radar/training/velodyne/*.bin scans (a VoD folder)")
    have = {canonical_column(c) for c in read_cloud(files[0]).columns}
    missing = [c for c in columns if canonical_column(c) not in have]
    if missing:  # every scan would be refused by the node: nothing to time
        cause = f"reads columns {' '.join(columns)}; the --data scans have no {' '.join(missing)}"
        raise MsdnetError("--model", cause)
    check_writable(out, "into")  # before any work
    doc = live_bench(
        resolve_model(model),
        files,
        threads,
        messages,
        ladder_messages,
        storm_hz,
        storm_s,
        input_type=input_type,
    )
    doc["note"] = note or "nothing noted about the machine's load"
    stem = "live" if input_type == "pointcloud2" else f"live-{input_type}"
    write_markdown_and_json(doc, markdown(doc), out, stem)
    click.echo(markdown(doc))
