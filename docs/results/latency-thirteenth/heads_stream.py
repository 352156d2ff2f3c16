"""Whole frames on a stream with each provider's head pick, and with the coarse-to-fine head forced:
every frame of a dataset once, in order, through one pipeline per variant, interleaved by frame
(the order rotated), as a sensor would feed them.

    python docs/results/latency-thirteenth/heads_stream.py models/astyx-lite astyx \\
        ../shared/data/astyx_hires2019 --steps 2 --variants cpu,auto,auto-bf16:gated,auto-bf16

A variant is a provider, with ``:gated`` to run the coarse-to-fine head at the manifest's gate
whatever ``auto`` picked. Prints each variant's head and median ms a frame (all frames, first,
middle and last 100), its median head ms and decoded points, and the last variant's time over each
other's, paired by frame. The ``auto`` picks are those of the cache under ``$XDG_CACHE_HOME``.
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
@click.option("--variants", default="cpu,auto,auto-bf16:gated,auto-bf16", show_default=True)
@click.option("--threads", type=int, default=2, show_default=True)
def main(model: Path, dataset: str, data: Path, steps: int | None, variants: str, threads: int) -> None:
    names = variants.split(",")
    pipes = {v: Pipeline.from_dir(model, provider=v.split(":")[0], threads=threads) for v in names}
    for v, p in pipes.items():
        if v.endswith(":gated"):
            p.gate = p.artifact.gate
        click.echo(f"{v}: {'dense head' if p.gate is None else f'coarse-to-fine head, gate {p.gate:.4g}'}")
    frames = load_frames(data, dataset, None, pipes[names[0]])
    for p in pipes.values():
        p.warmup()
    total: dict[str, list[float]] = {v: [] for v in names}
    head: dict[str, list[float]] = {v: [] for v in names}
    points: dict[str, list[int]] = {v: [] for v in names}
    for i, (_, radar, _) in enumerate(frames):
        for v in names[i % len(names) :] + names[: i % len(names)]:
            res = pipes[v](radar, steps=steps)
            total[v].append(res.timings["total"] * 1e3)
            head[v].append(res.timings["head"] * 1e3)
            points[v].append(len(res.points))
    n = len(frames)
    for v in names:
        a = np.asarray(total[v])
        click.echo(
            f"{v:16s} {n} frames: median ms all {np.median(a):.2f} (first 100 {np.median(a[:100]):.2f}, "
            f"middle 100 {np.median(a[n // 2 - 50 : n // 2 + 50]):.2f}, last 100 {np.median(a[-100:]):.2f}); "
            f"head {np.median(head[v]):.2f} ms; {np.median(points[v]):.0f} points"
        )
    last = np.asarray(total[names[-1]])
    for v in names[:-1]:
        click.echo(f"{names[-1]} / {v}, paired by frame: {np.median(last / np.asarray(total[v])):.3f}")


if __name__ == "__main__":
    main()
