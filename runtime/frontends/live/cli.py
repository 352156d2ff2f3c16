"""``msdnet-node``: a live ROS 2 node over DDS that densifies a radar topic.

    msdnet-node --topic /radar/points [--input-type radar_scan] [--params-file node.yaml]

Subscribes the radar topic (``sensor_msgs/msg/PointCloud2`` or ``radar_msgs/msg/RadarScan``;
DDS ``rt/radar/points``) and publishes the dense cloud (``<topic>/dense``): float32 ``x y z
confidence``, the input's stamp and frame_id (or ``--target-frame``), plus the debug timing
topics and ``/diagnostics`` (``runtime/frontends/live/observe``). Every flag is a parameter of
``runtime/frontends/live/params`` and can come from a ROS 2 parameters file; ``--print-params``
prints the resolved parameters in that form and exits. No ROS install: the cyclonedds binding
(``pip install 'msdnet[live]'``) speaks RTPS, so a ROS 2 system on the same domain id sees the
node's topics. SIGINT / SIGTERM stop it within a second in any state (loading the model and
measuring engines included) and print the counters, the receive -> publish latency (p50 / p90 /
p99 / max) and the input points dropped, exit 0. The command ends the process itself
(``lifecycle``: ``os._exit`` once all is written): call ``node.serve`` to embed.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from msdnet.runtime.errors import EXIT_BAD_INPUT, MsdnetError, one_line_errors
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


def _named(origin: dict[str, str], name: str, check: Callable[[], Any]) -> Any:
    """``check()``, its MsdnetError re-named after where parameter ``name`` came from (the flag,
    or the parameters file and key)."""
    try:
        return check()
    except MsdnetError as err:
        raise MsdnetError(origin.get(name, name), err.cause) from None


def config_from(values: dict[str, Any], artifact: Any, origin: dict[str, str] | None = None) -> Any:
    """The resolved parameters -> NodeConfig, each checked against the model ``artifact``; one
    line naming the flag, or the parameters file and key (``origin``)."""
    from msdnet.runtime.frontends.densify import DensifyOptions
    from msdnet.runtime.frontends.live.checks import (
        check_extrinsic,
        check_identity,
        check_radar_scan_fields,
        check_topics,
        resolve_topic,
    )
    from msdnet.runtime.frontends.live.dds import check_domain
    from msdnet.runtime.frontends.live.node import NodeConfig
    from msdnet.runtime.io.rosbag import parse_field_map

    origin = origin or {}
    columns = tuple(artifact.inputs.columns)
    name, namespace = check_identity(values["node_name"], values["namespace"], origin)
    fqn = "/" + "/".join(t for t in f"{namespace}/{name}".split("/") if t)
    topic = _named(origin, "input_topic", lambda: resolve_topic(values["input_topic"], namespace, fqn))
    output = values["output_topic"]
    if output:
        output = _named(origin, "output_topic", lambda: resolve_topic(output, namespace, fqn))
    _named(origin, "domain_id", lambda: check_domain(values["domain_id"]))
    _named(origin, "fields", lambda: parse_field_map(values["fields"], columns))
    if values["input_type"] == "radar_scan":
        if values["field_preset"]:
            raise MsdnetError(
                origin.get("field_preset", "--field-preset"),
                "applies to PointCloud2 input only (a RadarScan's fields are fixed)",
            )
        _named(origin, "fields", lambda: check_radar_scan_fields(values["fields"], columns))
    if bool(values["target_frame"]) != bool(values["extrinsic"]):
        raise MsdnetError(
            origin.get("target_frame", "--target-frame"),
            "needs --extrinsic x,y,z,roll,pitch,yaw, and the other way round",
        )
    extrinsic = None
    if values["extrinsic"]:
        extrinsic = _named(origin, "extrinsic", lambda: check_extrinsic(values["extrinsic"], artifact.grid))
    delay = _named(origin, "testing_delay", lambda: _delay(values["testing_delay"]))
    options = DensifyOptions(
        steps=values["steps"] or None,
        threshold=values["threshold"] or None,
        seed=values["seed"],
        keep_radar=values["keep_radar"],
    )
    cfg = NodeConfig(
        topic=topic,
        domain_id=values["domain_id"],
        fields=tuple(values["fields"]),
        options=options,
        stats_every=values["stats_every"],
        stats_json=Path(values["stats_json"]) if values["stats_json"] else None,
        input_type=values["input_type"],
        input_reliable=values["input_reliability"] == "reliable",
        output_topic=output,
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
        testing_delay=delay,
        node_name=name,
        namespace=namespace,
        diagnostics_period_s=values["diagnostics_period_s"],
    )
    check_topics(cfg, origin)
    return cfg


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
    from_file = params.file_values(params_file, flags, given) if params_file else {}
    values, origin = params.resolve(from_file, flags, given, params_file)
    _check_stats_path(values, origin, params_file)
    if print_params:
        click.echo(params.dump(values), nl=False)
        return
    run(values, origin)


def _check_stats_path(values: dict[str, Any], origin: dict[str, str], params_file: Path | None) -> None:
    """The stats JSON overwrites none of the node's inputs: the parameters file, the trusted key,
    a file of the model folder."""
    if not values["stats_json"]:
        return
    stats = Path(values["stats_json"]).resolve()
    inputs = {"the parameters file": params_file, "the trusted key": values["trusted_key"] or None}
    for what, path in inputs.items():
        if path is not None and Path(path).resolve() == stats:
            raise MsdnetError(
                origin.get("stats_json", "--stats-json"), f"{stats} is {what}: it would be overwritten"
            )
    if (
        values["model"]
        and Path(values["model"]).exists()
        and Path(values["model"]).resolve() in stats.parents
    ):
        raise MsdnetError(origin.get("stats_json", "--stats-json"), f"{stats} is inside the model folder")


def run(values: dict[str, Any], origin: dict[str, str] | None = None) -> None:
    """Check everything, then serve until SIGINT / SIGTERM and end the process (``lifecycle``):
    a signal at any point, the model loading included, ends it with exit 0 and the stats."""
    from msdnet.runtime.frontends.live.lifecycle import Lifecycle

    # what the last words need, filled in as the node starts; "phase": what it is doing
    state: dict[str, Any] = {"pipe": None, "stats_json": None, "stats": None, "phase": "starting"}

    def echo(text: str) -> None:
        click.echo(text)
        sys.stdout.flush()

    def warn(text: str) -> None:
        click.echo(text, err=True)

    def report() -> None:  # the last words, whoever ends the process
        from msdnet.runtime.frontends.live.stats import NodeStats, engines_used, write_stats

        stats = state["stats"] or NodeStats()
        phase = "serving" if life.serving_now() else state["phase"]
        if phase != "serving":
            warn(f"msdnet-node: stopped while {phase}, before serving")
        echo(stats.line())
        if state["stats_json"] is not None:
            engines = engines_used(state["pipe"], values["provider"])
            write_stats(state["stats_json"], stats, engines, phase)

    life = Lifecycle(report)
    life.install()  # first: every thread started after it (numpy's BLAS pool too) inherits the block
    try:
        if values["stats_json"]:
            from msdnet.runtime.io.atomic import check_writable

            check_writable(values["stats_json"])  # before any work: the stats are not lost at exit
            state["stats_json"] = Path(values["stats_json"])
        from msdnet.runtime.frontends.live.stats import NodeStats

        stats = state["stats"] = NodeStats()
        _start(values, origin or {}, state, life, stats, echo, warn)
    except MsdnetError as err:
        life.end(EXIT_BAD_INPUT, _renamed(err, origin or {}))
    life.end(0)


def _renamed(err: MsdnetError, origin: dict[str, str]) -> MsdnetError:
    """``err`` named after where its parameter came from (``--steps`` given in a parameters file is
    ``node.yaml: steps``); an error naming no parameter as it is."""
    by_flag = {p.flag: p.name for p in PARAMS} | {p.name: p.name for p in PARAMS}
    name = by_flag.get(str(err.path))
    if name is None or origin.get(name, str(err.path)) == str(err.path):
        return err
    return MsdnetError(origin[name], err.cause)


def _start(
    values: dict[str, Any],
    origin: dict[str, str],
    state: dict[str, Any],
    life: Any,
    stats: Any,
    echo: Callable[[str], None],
    warn: Callable[[str], None],
) -> None:
    """Load and check everything, then serve until ``life.stop``."""
    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.frontends.live.dds import cyclonedds
    from msdnet.runtime.frontends.live.messages import preset_note
    from msdnet.runtime.frontends.live.node import serve
    from msdnet.runtime.frontends.model_args import check_model_options, resolve_model

    cyclonedds()  # the missing-extra line before anything else
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
    cfg = config_from(values, artifact, origin)
    state["phase"] = "loading the model"  # with provider auto and no cached picks: measuring engines
    pipe = Pipeline(artifact, provider=values["provider"], threads=values["threads"] or None)
    state["pipe"], state["phase"] = pipe, "warming up and joining DDS"
    preset = "radar_scan" if cfg.input_type == "radar_scan" else cfg.field_preset
    note = preset_note(preset, pipe.columns) if not cfg.fields else None
    if note:
        warn(f"msdnet-node: {note}")
    serve(pipe, cfg, life.stop, echo, warn, stats, life.serving)


if __name__ == "__main__":
    main()
