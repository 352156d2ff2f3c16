"""``msdnet-node``: a live ROS 2 node over DDS that densifies a radar PointCloud2 topic.

    msdnet-node --topic /radar/points [--domain-id 0] [--model DIR] [--field rcs=intensity]

Subscribes ``--topic`` (DDS ``rt/radar/points``, type ``sensor_msgs::msg::dds_::PointCloud2_``)
and publishes ``<topic>/dense``: float32 ``x y z confidence``, the input's stamp and frame_id.
No ROS install: the cyclonedds binding (``pip install 'msdnet[live]'``) speaks RTPS, so a ROS 2
system on the same domain id sees the node's topics. QoS and the real-time rules:
``runtime/frontends/live/dds`` and ``runtime/frontends/live/node``. SIGINT / SIGTERM stop it within a
second and print the counters and the receive -> publish latency (p50 / p90 / p99 / max). The
command ends the process itself (``os._exit`` once all is written): call :func:`serve` to embed.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

import click

from msdnet.runtime.errors import MsdnetError, one_line_errors


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--topic", default="/radar/points", show_default=True, help="ROS 2 PointCloud2 topic to densify."
)
@click.option(
    "--domain-id",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="DDS domain (ROS_DOMAIN_ID).",
)
@click.option("--model", type=click.Path(path_type=Path), help="msdnet-export folder [bundled].")
@click.option(
    "--provider",
    default="cpu",
    show_default=True,
    help="cpu, cpu-shared, auto, auto-bf16, openvino, openvino-bf16, cuda or tensorrt.",
)
@click.option("--threads", type=click.IntRange(min=1), help="Intra-op threads.")
@click.option(
    "--field", "fields", multiple=True, metavar="COLUMN=FIELD", help="Map a model column to a field."
)
@click.option("--steps", type=click.IntRange(min=1), help="DDIM steps [manifest T_m].")
@click.option("--threshold", type=float, help="Occupancy threshold [manifest].")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Noise seed.")
@click.option("--keep-radar", is_flag=True, help="Also publish the input radar points in the grid.")
@click.option(
    "--stats-every",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Stats line every N messages.",
)
@click.option("--stats-json", type=click.Path(path_type=Path), help="Write the final stats as JSON here.")
@click.option(
    "--trusted-key", type=click.Path(path_type=Path), help="Ed25519 public key: refuse an unsigned model."
)
@one_line_errors
def main(
    topic: str,
    domain_id: int,
    model: Path | None,
    provider: str,
    threads: int | None,
    fields: tuple[str, ...],
    steps: int | None,
    threshold: float | None,
    seed: int,
    keep_radar: bool,
    stats_every: int,
    stats_json: Path | None,
    trusted_key: Path | None,
) -> None:
    """Densify a ROS 2 radar PointCloud2 topic live, over DDS (no ROS install)."""
    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.frontends.densify import DensifyOptions
    from msdnet.runtime.frontends.live.dds import check_domain, cyclonedds
    from msdnet.runtime.frontends.live.idl import dds_topic
    from msdnet.runtime.frontends.live.node import NodeConfig, serve, write_stats
    from msdnet.runtime.frontends.model_args import check_model_options, resolve_model
    from msdnet.runtime.io.rosbag import parse_field_map

    cyclonedds()  # the missing-extra line before anything else
    dds_topic(topic)
    check_domain(domain_id)
    artifact = check_model_options(resolve_model(model), trusted_key, provider, threshold, steps)
    parse_field_map(fields, artifact.inputs.columns)
    if stats_json is not None and stats_json.is_dir():
        raise MsdnetError(stats_json, "is a folder; --stats-json takes a file path")
    options = DensifyOptions(steps=steps, threshold=threshold, seed=seed, keep_radar=keep_radar)
    cfg = NodeConfig(topic, domain_id, fields, options, stats_every, stats_json)
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    pipe = Pipeline(artifact, provider=provider, threads=threads)

    def echo(text: str) -> None:
        click.echo(text)
        sys.stdout.flush()

    def warn(text: str) -> None:
        click.echo(text, err=True)

    stats = serve(pipe, cfg, stop, echo, warn)
    echo(stats.line())
    if stats_json is not None:
        write_stats(stats_json, stats)
    sys.stdout.flush()
    sys.stderr.flush()
    # Everything is written and the DDS participant deleted; skip the interpreter's teardown of
    # numba and onnxruntime (~1 s here, freeing only memory), so SIGTERM -> exit stays well under 1 s.
    os._exit(0)


if __name__ == "__main__":
    main()
