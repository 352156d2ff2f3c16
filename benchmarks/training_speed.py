"""``msdnet-bench training-speed``: the step time of a training run before and after the speed-ups,
interleaved on one machine, and the evidence that both learn the same thing.

Two worker processes (benchmarks/training_speed_worker.py) hold the same model from the same seed:

- **before**: the exact loss over the whole full scale (``full_scale_rate`` 1) and OpenMP's
  default wait policy (threads spin at barriers);
- **after**: the full scale on sparse rows (``--full-scale-rate``, unbiased) and passive OpenMP
  threads, as ``msdnet-train`` now runs.

Each round asks the two sides in turn (ABBA order) for one training step on the same batch
(collate, forward, backward, clipping, Adam), so the machine's load falls on both alike. The
first ``--warmup`` rounds are not timed. After the rounds both score the same held-out batches
(the selection slice) with the exact loss: what was learned in the same steps.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import statistics
import time
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Any

import click

from msdnet.benchmarks.machine import machine_info, shown_path
from msdnet.benchmarks.stages import write_markdown_and_json
from msdnet.benchmarks.training_speed_worker import Side, serve
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import checks_outputs

KINDS = ("teacher", "student")
READY_TIMEOUT_S = 900.0  # reading and preprocessing the frames on a loaded machine


@contextmanager
def _sides(before: Side, after: Side):  # -> Iterator[dict[str, Connection]]
    """The two worker processes, each started with its own OpenMP wait policy."""
    ctx = mp.get_context("spawn")
    procs, conns = [], {}
    saved = os.environ.get("OMP_WAIT_POLICY")
    try:
        for side, policy in ((before, None), (after, "PASSIVE")):
            if policy is None:  # OpenMP's default, as before msdnet.training set the passive one
                os.environ.pop("OMP_WAIT_POLICY", None)
            else:
                os.environ["OMP_WAIT_POLICY"] = policy
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=serve, args=(side, child), daemon=True)
            proc.start()
            procs.append(proc)
            conns[side.name] = parent
        if saved is None:
            os.environ.pop("OMP_WAIT_POLICY", None)
        else:
            os.environ["OMP_WAIT_POLICY"] = saved
        for name, conn in conns.items():
            if not conn.poll(READY_TIMEOUT_S):
                raise MsdnetError(
                    None, f"training-speed: the {name} side did not start in {READY_TIMEOUT_S:.0f} s"
                )
            status, text = conn.recv()
            if status != "ready":
                raise MsdnetError(None, f"training-speed: the {name} side failed: {text}")
        yield conns
    finally:
        for conn in conns.values():
            try:
                conn.send(("stop", None))
            except OSError:
                pass
        for proc in procs:
            proc.join(timeout=30)
            if proc.is_alive():
                proc.kill()


def _summary(times: list[float]) -> dict[str, float]:
    q = statistics.quantiles(times, n=10) if len(times) > 1 else [times[0]] * 9
    return {"median_s": statistics.median(times), "p10_s": q[0], "p90_s": q[-1], "steps": len(times)}


def measure(kind: str, opts: dict[str, Any]) -> dict[str, Any]:
    """Interleaved step times and the held-out loss of both sides for one model kind."""
    common = dict(kind=kind, dataset=opts["dataset"], data=str(opts["data"]), preset=opts["preset"],
                  batch_size=opts["batch_size"], threads=opts["threads"], steps=opts["rounds"],
                  score_batches=opts["score_batches"], seed=opts["seed"])  # fmt: skip
    before = Side(name="before", full_scale_rate=1.0, **common)
    after = Side(name="after", full_scale_rate=opts["full_scale_rate"], **common)
    times: dict[str, list[float]] = {"before": [], "after": []}
    loads = []
    with _sides(before, after) as conns:
        start = {n: _score(c) for n, c in conns.items()}
        bar = click.progressbar(range(opts["rounds"]), label=f"{kind} steps, before/after interleaved")
        with bar:
            for r in bar:
                order = ("before", "after") if r % 2 == 0 else ("after", "before")
                for name in order:
                    conns[name].send(("step", r))
                    took = conns[name].recv()
                    if r >= opts["warmup"]:
                        times[name].append(took)
                loads.append(os.getloadavg()[0])
        end = {n: _score(c) for n, c in conns.items()}
    b, a = _summary(times["before"]), _summary(times["after"])
    return {
        "before": b | {"loss_start": start["before"], "loss_end": end["before"]},
        "after": a | {"loss_start": start["after"], "loss_end": end["after"]},
        "step_over_before": a["median_s"] / b["median_s"],
        "loss_end_relative_difference": (end["after"] - end["before"]) / end["before"],
        "load_average_1min": {"min": min(loads), "max": max(loads), "mean": statistics.fmean(loads)},
        "sides": {"before": asdict(before), "after": asdict(after)},
    }


def _score(conn) -> float:
    conn.send(("score", None))
    return float(conn.recv())


def speed_markdown(doc: dict[str, Any]) -> str:
    """The results page: step times, ratio, held-out loss of both sides."""
    c = doc["config"]
    lines = [
        "# Training step time, before and after (interleaved)",
        "",
        f"{c['preset']} preset, batch {c['batch_size']}, {c['dataset']} fitted frames, {c['threads']} torch "
        f"threads; {c['rounds']} steps each side, the first {c['warmup']} untimed. After: full-scale rate "
        f"{c['full_scale_rate']}, passive OpenMP threads. Loss: the exact loss on the same held-out batches "
        "after the same steps.",
        "",
        "| model | before s/step (p10-p90) | after s/step (p10-p90) | after / before | "
        "held-out loss start | before, end | after, end | difference | load average |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for kind in KINDS:
        if kind not in doc["kinds"]:
            continue
        k = doc["kinds"][kind]
        b, a, la = k["before"], k["after"], k["load_average_1min"]
        lines.append(
            f"| {kind} | {b['median_s']:.3f} ({b['p10_s']:.2f}-{b['p90_s']:.2f}) | "
            f"{a['median_s']:.3f} ({a['p10_s']:.2f}-{a['p90_s']:.2f}) | {k['step_over_before']:.3f} | "
            f"{b['loss_start']:.4f} | {b['loss_end']:.4f} | {a['loss_end']:.4f} | "
            f"{100 * k['loss_end_relative_difference']:+.1f} % | {la['min']:.1f}-{la['max']:.1f} |"
        )
    m = doc["machine"]
    lines += ["", f"Machine: {m['cpu']} x{m['logical_cores']}, {m['system']}."]
    return "\n".join(lines) + "\n"


@click.command("training-speed", context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--dataset", required=True, type=click.Choice(["astyx", "vod", "sim", "sim-astyx"]), help="Data layout."
)
@click.option(
    "--data",
    required=True,
    type=click.Path(path_type=Path, exists=True, file_okay=False),
    help="Dataset root.",
)
@click.option(
    "--kind", "kinds", multiple=True, type=click.Choice(KINDS), help="Models to time [teacher and student]."
)
@click.option(
    "--preset",
    type=click.Choice(["tiny", "lite", "paper"]),
    default="lite",
    show_default=True,
    help="Model preset.",
)
@click.option(
    "--batch-size", type=click.IntRange(min=1), default=4, show_default=True, help="Frames per step."
)
@click.option(
    "--threads", type=click.IntRange(min=1), default=2, show_default=True, help="torch threads per side."
)
@click.option("--rounds", type=click.IntRange(min=3), default=24, show_default=True, help="Steps per side.")
@click.option(
    "--warmup", type=click.IntRange(min=0), default=2, show_default=True, help="Untimed first rounds."
)
@click.option(
    "--full-scale-rate",
    type=click.FloatRange(0.0, 1.0, min_open=True),
    default=0.05,
    show_default=True,
    help="The after side's share of far full-scale voxels (msdnet-train --full-scale-rate).",
)
@click.option(
    "--score-batches",
    type=click.IntRange(min=1),
    default=4,
    show_default=True,
    help="Held-out batches scored exactly before and after the steps.",
)
@click.option(
    "--seed", type=int, default=0, show_default=True, help="Seed of weights and draws (both sides)."
)
@click.option(
    "--out", required=True, type=click.Path(path_type=Path), help="Folder for results.json / results.md."
)
@one_line_errors
@checks_outputs(out="into")  # before any work
def training_speed_command(out: Path, kinds: tuple[str, ...], **opts: Any) -> None:
    """Training step time before and after the speed-ups, interleaved, and the held-out loss both
    reach in the same steps (needs the [train] extra)."""  # fmt: skip
    if opts["warmup"] >= opts["rounds"]:
        raise MsdnetError("--warmup", f"must be below --rounds ({opts['rounds']}), got {opts['warmup']}")
    try:
        import torch  # noqa: F401
    except ImportError:
        raise MsdnetError(None, "training-speed needs torch: pip install 'msdnet[train]'") from None
    started = time.time()
    results = {kind: measure(kind, opts) for kind in (kinds or KINDS)}
    doc = {
        "config": {**{k: (shown_path(v) if k == "data" else v) for k, v in opts.items()}},
        "kinds": results,
        "ratios": {f"{k}_step_over_before": v["step_over_before"] for k, v in results.items()},
        "seconds": round(time.time() - started, 1),
        "machine": machine_info(sgemm=False).to_json(),
    }
    write_markdown_and_json(doc, speed_markdown(doc), out, "results")
    click.echo(speed_markdown(doc))
