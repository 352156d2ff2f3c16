"""``msdnet-node``: a live ROS 2 node over DDS that densifies a radar topic.

    msdnet-node --topic /radar/points [--input-type radar_scan] [--params-file node.yaml]

Subscribes the radar topic (``sensor_msgs/msg/PointCloud2`` or ``radar_msgs/msg/RadarScan``;
DDS ``rt/radar/points``) and publishes the dense cloud (``<topic>/dense``): float32 ``x y z
confidence``, the input's stamp and frame_id (or ``--target-frame``), plus the debug timing
topics and ``/diagnostics`` (``runtime/frontends/live/observe``). Every flag is a parameter of
``runtime/frontends/live/params`` and can come from a ROS 2 parameters file; ``--print-params``
prints the resolved parameters in that form and exits. No ROS install: the cyclonedds binding
(``pip install 'msdnet[live]'``) speaks RTPS, so a ROS 2 system on the same domain id sees the
node's topics. SIGINT / SIGTERM stop it within a second and print the counters, the receive ->
publish latency (p50 / p90 / p99 / max) and the input points dropped. The command ends the
process itself (``os._exit`` once all is written): call :func:`serve` to embed.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.frontends.live.params import PARAMS


def _options(func: Callable[..., Any]) -> Callable[..., Any]:
    """One click option per parameter; every default None, so a flag not given is known."""
    for p in reversed(PARAMS):
        text = p.help + (f" [default: {p.default}]" if p.default not in ("", []) else "")
        metavar = "|".join(c for c in p.choices if c) if p.choices else None
        if p.kind == "bool":
            opt = click.option(
                f"{p.flag}/--no-{p.flag[2:]}", p.name, default=None, help=text, hidden=p.hidden
            )
        elif p.kind == "list":
            opt = click.option(p.flag, p.name, multiple=True, metavar="COLUMN=FIELD", help=text)
        else:
            kind = {"int": int, "float": float, "str": str}[p.kind]
            opt = click.option(
                p.flag, p.name, type=kind, default=None, help=text, hidden=p.hidden, metavar=metavar
            )
        func = opt(func)
    return func


def _delay(text: str) -> tuple[int, int, float] | None:
    if not text:
        return None
    try:
        first, stop, ms = text.split(":")
        out = (int(first), int(stop), float(ms))
    except ValueError:
        out = None
    if out is None or out[0] < 0 or out[1] < out[0] or not 0 <= out[2] < 60_000:
        raise MsdnetError("--testing-delay", f"expected START:STOP:MS, got {text!r}")
    return out


def config_from(values: dict[str, Any], columns: tuple[str, ...]) -> Any:
    """The resolved parameters -> NodeConfig, each checked (one line naming the flag)."""
    from msdnet.runtime.frontends.densify import DensifyOptions
    from msdnet.runtime.frontends.live.dds import check_domain
    from msdnet.runtime.frontends.live.idl import dds_topic
    from msdnet.runtime.frontends.live.node import NodeConfig
    from msdnet.runtime.io.pairing.transforms import parse_extrinsic
    from msdnet.runtime.io.rosbag import parse_field_map

    dds_topic(values["input_topic"])
    if values["output_topic"]:
        try:
            dds_topic(values["output_topic"])
        except MsdnetError as err:
            raise MsdnetError("--output-topic", err.cause) from None
    check_domain(values["domain_id"])
    parse_field_map(values["fields"], columns)
    if values["input_type"] == "radar_scan" and values["field_preset"]:
        raise MsdnetError(
            "--field-preset", "applies to PointCloud2 input only (a RadarScan's fields are fixed)"
        )
    extrinsic = None
    if bool(values["target_frame"]) != bool(values["extrinsic"]):
        raise MsdnetError("--target-frame", "needs --extrinsic x,y,z,roll,pitch,yaw, and the other way round")
    if values["extrinsic"]:
        parse_extrinsic(values["extrinsic"])
        extrinsic = tuple(float(v) for v in values["extrinsic"].split(","))
    options = DensifyOptions(
        steps=values["steps"] or None,
        threshold=values["threshold"] or None,
        seed=values["seed"],
        keep_radar=values["keep_radar"],
    )
    return NodeConfig(
        topic=values["input_topic"],
        domain_id=values["domain_id"],
        fields=tuple(values["fields"]),
        options=options,
        stats_every=values["stats_every"],
        stats_json=Path(values["stats_json"]) if values["stats_json"] else None,
        input_type=values["input_type"],
        input_reliable=values["input_reliability"] == "reliable",
        output_topic=values["output_topic"],
        field_preset=values["field_preset"],
        target_frame=values["target_frame"],
        extrinsic=extrinsic,
        output_reliable=values["output_reliability"] == "reliable",
        publish_debug=values["publish_debug"],
        debug_msgs_type=values["debug_msgs_type"],
        publish_diagnostics=values["publish_diagnostics"],
        max_allowed_processing_time_ms=values["max_allowed_processing_time_ms"],
        max_acceptable_consecutive_delay_ms=values["max_acceptable_consecutive_delay_ms"],
        foxglove=values["foxglove"],
        foxglove_host=values["foxglove_host"],
        foxglove_port=values["foxglove_port"],
        testing_delay=_delay(values["testing_delay"]),
    )


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--params-file",
    type=click.Path(path_type=Path, dir_okay=False),
    help="ROS 2 parameters file (msdnet_node: ros__parameters: ...); flags given win.",
)
@click.option(
    "--print-params", is_flag=True, help="Print the resolved parameters as a parameters file; exit."
)
@_options
@one_line_errors
def main(params_file: Path | None, print_params: bool, **flags: Any) -> None:
    """Densify a ROS 2 radar topic (PointCloud2 or RadarScan) live, over DDS (no ROS install)."""
    from msdnet.runtime.frontends.live import params

    given = {k for k, v in flags.items() if v is not None and v != ()}
    flags = {k: list(v) if isinstance(v, tuple) else v for k, v in flags.items()}
    values = params.resolve(params.read_file(params_file) if params_file else {}, flags, given)
    if print_params:
        click.echo(params.dump(values), nl=False)
        return
    run(values)


def run(values: dict[str, Any]) -> None:
    """Check everything, then serve until SIGINT / SIGTERM and exit the process."""
    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.frontends.live.dds import cyclonedds
    from msdnet.runtime.frontends.live.messages import preset_note
    from msdnet.runtime.frontends.live.node import engines_used, serve, write_stats
    from msdnet.runtime.frontends.model_args import check_model_options, resolve_model
    from msdnet.runtime.io.atomic import check_writable

    cyclonedds()  # the missing-extra line before anything else
    if values["stats_json"]:
        check_writable(values["stats_json"])  # before any work: the stats are not lost at exit
    if values["foxglove"]:
        from msdnet.runtime.frontends.live.foxglove_view import _foxglove

        _foxglove()
    model = Path(values["model"]) if values["model"] else None
    trusted = Path(values["trusted_key"]) if values["trusted_key"] else None
    artifact = check_model_options(
        resolve_model(model),
        trusted,
        values["provider"],
        values["threshold"] or None,
        values["steps"] or None,
    )
    cfg = config_from(values, tuple(artifact.inputs.columns))
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    pipe = Pipeline(artifact, provider=values["provider"], threads=values["threads"] or None)

    def echo(text: str) -> None:
        click.echo(text)
        sys.stdout.flush()

    def warn(text: str) -> None:
        click.echo(text, err=True)

    preset = "radar_scan" if cfg.input_type == "radar_scan" else cfg.field_preset
    note = preset_note(preset, pipe.columns) if not cfg.fields else None
    if note:
        warn(f"msdnet-node: {note}")
    stats = serve(pipe, cfg, stop, echo, warn)
    echo(stats.line())
    if cfg.stats_json is not None:
        write_stats(cfg.stats_json, stats, engines_used(pipe, values["provider"]))
    sys.stdout.flush()
    sys.stderr.flush()
    # Everything is written and the DDS participant deleted; skip the interpreter's teardown of
    # numba and onnxruntime (~1 s here, freeing only memory), so SIGTERM -> exit stays well under 1 s.
    os._exit(0)


if __name__ == "__main__":
    main()
