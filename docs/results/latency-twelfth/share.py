"""Do two OpenVINO compiled copies of one graph share the work of a new input shape?

    python docs/results/latency-twelfth/share.py models/astyx-lite

For the encoder and the coarse-to-fine head, in f32 and bf16: two copies, each warmed on the first
of ``provider_auto``'s seeded scans; then on each other scan (a shape new to both) the first copy,
the second copy, and the first again. Medians in ms.
"""

from __future__ import annotations

import os
import time

import click
import numpy as np

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

from msdnet.runtime.engine import provider_auto  # noqa: E402
from msdnet.runtime.engine.openvino_session import OpenVinoSession  # noqa: E402
from msdnet.runtime.engine.pipeline import Pipeline  # noqa: E402


@click.command()
@click.argument("model", type=click.Path(exists=True))
@click.option("--threads", type=int, default=2, show_default=True)
def main(model: str, threads: int) -> None:
    pipe = Pipeline.from_dir(model, threads=threads)
    stream = provider_auto.stream_inputs(pipe, threads)
    for graph in ("encoder.onnx", "recon_head_sparse.onnx"):
        for precision in ("f32", "bf16"):
            a, b = (OpenVinoSession(pipe.artifact.graphs[graph], threads, precision) for _ in range(2))
            for s in (a, b):
                s.run(None, stream.feeds[0][graph][0])
                s.run(None, stream.feeds[0][graph][0])
            ms: list[list[float]] = [[], [], []]  # first copy, second copy, first copy again
            for k in range(1, len(stream.feeds)):
                feed = stream.feeds[k][graph][0]  # one call: these graphs make one a frame
                order = (a, b, a) if k % 2 else (b, a, b)
                for i, s in enumerate(order):
                    t0 = time.perf_counter()
                    s.run(None, feed)
                    ms[i].append((time.perf_counter() - t0) * 1e3)
            first, second, again = (float(np.median(v)) for v in ms)
            click.echo(
                f"{graph} {precision}: first copy on a new shape {first:.2f} ms, second copy {second:.2f}, "
                f"first copy again {again:.2f}"
            )


if __name__ == "__main__":
    main()
