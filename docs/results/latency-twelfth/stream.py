"""Whole-frame latency on a stream: every frame of a dataset once, in order, through one pipeline
per provider (interleaved by frame, the order rotated), as a sensor would feed them.

    python docs/results/latency-twelfth/stream.py models/astyx-lite astyx ../shared/data/astyx_hires2019 \
        --steps 2 --providers cpu,auto,auto-bf16 [--passes 1]

Prints, per provider, the median ms of the first 100, middle 100 and last 100 frames and of all,
the median head ms and decoded points; then the last provider's time over each other's, paired by
frame. With ``--passes 2`` the stream is run again (every input then seen before: what a benchmark
that repeats its frames measures). A provider with ``:gated`` runs the coarse-to-fine head at the
manifest's gate whatever ``auto`` picked (``runtime/engine/provider_head``; the thirteenth cycle:
``--providers cpu,auto,auto-bf16:gated,auto-bf16``). The ``auto`` picks are those of the cache under
``$XDG_CACHE_HOME`` (point it at an empty folder to measure them afresh).
"""

from __future__ import annotations

import os
from pathlib import Path

import click
import numpy as np

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

from msdnet.benchmarks.latency.quality import load_frames  # noqa: E402
from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402


@click.command()
@click.argument("model", type=click.Path(exists=True, path_type=Path))
@click.argument("dataset")
@click.argument("data", type=click.Path(exists=True, path_type=Path))
@click.option("--steps", type=int, default=None, help="T_m [the manifest's].")
@click.option("--providers", default="cpu,auto,auto-bf16", show_default=True)
@click.option("--threads", type=int, default=2, show_default=True)
@click.option("--passes", type=int, default=1, show_default=True)
def main(
    model: Path, dataset: str, data: Path, steps: int | None, providers: str, threads: int, passes: int
) -> None:
    names = providers.split(",")
    pipes = {p: Pipeline.from_dir(model, provider=p.split(":")[0], threads=threads) for p in names}
    for name, p in pipes.items():
        if name.endswith(":gated"):
            p.gate = p.artifact.gate
        if p.auto is not None:
            click.echo("\n".join(p.auto.lines()[:-1]))
        click.echo(f"{name}: {'dense head' if p.gate is None else f'coarse-to-fine head, gate {p.gate:.4g}'}")
    frames = load_frames(data, dataset, None, pipes[names[0]])
    for p in pipes.values():
        p.warmup()
    for k in range(passes):
        ms: dict[str, list[float]] = {p: [] for p in names}
        head: dict[str, list[float]] = {p: [] for p in names}
        points: dict[str, list[int]] = {p: [] for p in names}
        for i, (_, radar, _) in enumerate(frames):
            for p in names[i % len(names) :] + names[: i % len(names)]:
                res = pipes[p](radar, steps=steps)
                ms[p].append(res.timings["total"] * 1e3)
                head[p].append(res.timings["head"] * 1e3)
                points[p].append(len(res.points))
        n = len(frames)
        for p, t in ms.items():
            a = np.asarray(t)
            click.echo(
                f"pass {k} {p:10s} {n} frames: median ms first 100 {np.median(a[:100]):.2f}, middle 100 "
                f"{np.median(a[n // 2 - 50 : n // 2 + 50]):.2f}, last 100 {np.median(a[-100:]):.2f}, "
                f"all {np.median(a):.2f}; head {np.median(head[p]):.2f} ms; {np.median(points[p]):.0f} points"
            )
        last = np.asarray(ms[names[-1]])
        for p in names[:-1]:
            ratio = float(np.median(last / np.asarray(ms[p])))
            click.echo(f"pass {k} {names[-1]} / {p}, paired by frame: {ratio:.3f}")


if __name__ == "__main__":
    main()
