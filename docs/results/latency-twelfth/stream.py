"""Whole-frame latency on a stream: every frame of a dataset once, in order, through one pipeline
per provider (interleaved by frame, the order rotated), as a sensor would feed them.

    python docs/results/latency-twelfth/stream.py models/astyx-lite astyx ../shared/data/astyx_hires2019 \
        --steps 2 --providers cpu,auto,auto-bf16 [--passes 1]

Prints, per provider, the median ms of the first 100, middle 100 and last 100 frames and of all;
with ``--passes 2`` the stream is run again (every input then seen before: what a benchmark that
repeats its frames measures). The ``auto`` picks are those of the cache under ``$XDG_CACHE_HOME``
(point it at an empty folder to measure them afresh).
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
    pipes = {p: Pipeline.from_dir(model, provider=p, threads=threads) for p in names}
    for p in pipes.values():
        if p.auto is not None:
            click.echo("\n".join(p.auto.lines()[:-1]))
    frames = load_frames(data, dataset, None, pipes[names[0]])
    for p in pipes.values():
        p.warmup()
    for k in range(passes):
        ms: dict[str, list[float]] = {p: [] for p in names}
        for i, (_, radar, _) in enumerate(frames):
            for p in names[i % len(names) :] + names[: i % len(names)]:
                ms[p].append(pipes[p](radar, steps=steps).timings["total"] * 1e3)
        n = len(frames)
        for p, t in ms.items():
            a = np.asarray(t)
            click.echo(
                f"pass {k} {p:10s} {n} frames: median ms first 100 {np.median(a[:100]):.2f}, middle 100 "
                f"{np.median(a[n // 2 - 50 : n // 2 + 50]):.2f}, last 100 {np.median(a[-100:]):.2f}, "
                f"all {np.median(a):.2f}"
            )


if __name__ == "__main__":
    main()
