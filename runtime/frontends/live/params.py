"""``msdnet-node``'s parameters: one table, the command line and a ROS 2 parameters file.

Every flag is a parameter: ``--stats-every`` is ``stats_every``. ``--params-file node.yaml`` reads
ROS 2's form (``params_file``: the limits it is read with, and the section keys)::

    msdnet_node:            # or /msdnet_node, /ns/name, /** (every node)
      ros__parameters:
        input_topic: /radar/points
        input_type: radar_scan
        max_allowed_processing_time_ms: 100.0

The node's name and namespace are ``--node-name`` / ``--namespace``, else ``node_name`` /
``namespace`` of the file's ``/**`` or ``msdnet_node`` section, else ``msdnet_node`` in ``/``. The
sections that apply are ``/**`` and the patterns matching the node's fully qualified name, then the
section that named it, then the node's own section (the last wins); sections for other nodes are
skipped, as ``ros2 run --params-file`` does. A flag given on the command line wins over the file.
Unknown keys, values of the wrong type and values outside their range are one-line errors naming
the file and key (:func:`resolve` keeps where each value came from: ``origin``). :func:`dump`
writes the resolved parameters back in the same form (``--print-params``), which a
``--params-file`` reproduces.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from msdnet.runtime.errors import MsdnetError

NODE_NAME = "msdnet_node"  # the node's default name (ROS 2: its name, in namespace "/")
MAX_THREADS = 256  # more intra-op threads than this is a typo, and would only exhaust the machine


@dataclass(frozen=True)
class Param:
    """One parameter of the table below."""

    name: str  # parameter name (the file's key); the flag is --name with dashes unless FLAG_NAMES
    kind: str  # bool, int, float, str or list (of strings)
    default: Any  # value when neither the file nor a flag gives one
    help: str  # one line for --help and the docs' table
    choices: tuple[str, ...] = ()  # allowed values of a str parameter (empty: any)
    low: float | None = None  # smallest allowed number
    hidden: bool = False  # left out of --help and of --print-params unless set
    high: float | None = None  # largest allowed number

    @property
    def flag(self) -> str:
        return "--" + FLAG_NAMES.get(self.name, self.name.replace("_", "-"))


FLAG_NAMES = {
    "input_topic": "topic",
    "fields": "field",
    "diagnostics_period_s": "diagnostics-period",
}  # flags not named after their parameter

PARAMS: tuple[Param, ...] = (
    Param("node_name", "str", NODE_NAME, "ROS 2 node name: ~/debug topics and diagnostics follow it."),
    Param("namespace", "str", "/", "ROS 2 namespace of the node, e.g. /sensing/radar/front."),
    Param("input_topic", "str", "/radar/points", "ROS 2 topic of the radar scans."),
    Param(
        "input_type",
        "str",
        "pointcloud2",
        "Message type of input_topic: sensor_msgs/msg/PointCloud2 or radar_msgs/msg/RadarScan.",
        choices=("pointcloud2", "radar_scan"),
    ),
    Param(
        "input_reliability",
        "str",
        "best_effort",
        "QoS reliability of the radar subscriber: best_effort (sensor data, matches every publisher) "
        "or reliable (matches reliable publishers only; messages of many MB arrive whole).",
        choices=("best_effort", "reliable"),
    ),
    Param("output_topic", "str", "", "Dense cloud topic; empty: input_topic + /dense."),
    Param("domain_id", "int", 0, "DDS domain (ROS_DOMAIN_ID).", low=0, high=232),
    Param("model", "str", "", "shipped model name or msdnet-export folder; empty: sim-lite."),
    Param(
        "provider",
        "str",
        "auto",
        "cpu, cpu-shared, auto, auto-bf16, openvino, openvino-bf16, cuda or tensorrt.",
    ),
    Param("threads", "int", 0, "Intra-op threads; 0: onnxruntime's default.", low=0, high=MAX_THREADS),
    Param(
        "field_preset",
        "str",
        "",
        "PointCloud2 field names of a sensor layout: vod, astyx, ars548 (nebula), ti; empty: by name.",
        choices=("", "vod", "astyx", "ars548", "ti"),
    ),
    Param("fields", "list", [], "Map a model column to an input field: COLUMN=FIELD (repeatable)."),
    Param("steps", "int", 0, "DDIM steps; 0: the manifest's T_m.", low=0, high=10_000),
    Param("threshold", "float", 0.0, "Occupancy threshold in (0, 1); 0: the manifest's.", low=0.0),
    Param("seed", "int", 0, "Noise seed.", low=0, high=2**63 - 1),
    Param("keep_radar", "bool", False, "Also publish the input radar points in the grid, with their fields."),
    Param("target_frame", "str", "", "Publish in this frame (needs extrinsic); empty: the input's frame."),
    Param(
        "extrinsic",
        "str",
        "",
        "x,y,z,roll,pitch,yaw (m, rad): the radar's pose in target_frame.",
    ),
    Param(
        "output_reliability",
        "str",
        "reliable",
        "QoS reliability of the dense cloud publisher.",
        choices=("reliable", "best_effort"),
    ),
    Param(
        "publish_debug",
        "bool",
        True,
        "Publish ~/debug/processing_time_ms, cyclic_time_ms, pipeline_latency_ms.",
    ),
    Param(
        "debug_msgs_type",
        "str",
        "autoware_internal_debug_msgs",
        "Package of the debug topics' Float64Stamped.",
        choices=("autoware_internal_debug_msgs", "tier4_debug_msgs"),
    ),
    Param("publish_diagnostics", "bool", True, "Publish diagnostic_msgs/DiagnosticArray on /diagnostics."),
    Param(
        "diagnostics_period_s",
        "float",
        1.0,
        "Period of /diagnostics, carrying the latest state (diagnostic_updater's period).",
        low=0.01,
        high=3600.0,
    ),
    Param(
        "max_allowed_processing_time_ms",
        "float",
        100.0,
        "Diagnostics WARN when one scan's processing time is above this.",
        low=0.0,
        high=3.6e6,
    ),
    Param(
        "max_acceptable_consecutive_delay_ms",
        "float",
        1000.0,
        "Diagnostics ERROR when processing stays above the limit for longer than this.",
        low=0.0,
        high=3.6e6,
    ),
    Param("foxglove", "bool", False, "Serve the radar and dense clouds to Foxglove over WebSocket."),
    Param("foxglove_host", "str", "127.0.0.1", "Address the Foxglove server binds."),
    Param("foxglove_port", "int", 8765, "Foxglove server port; 0: any free port.", low=0, high=65535),
    Param("stats_every", "int", 0, "Stats line every N messages; 0: only at exit.", low=0, high=2**31 - 1),
    Param("stats_json", "str", "", "Write the final stats as JSON here (checked writable at start)."),
    Param("trusted_key", "str", "", "Ed25519 public key: refuse an unsigned model."),
    Param(
        "testing_delay",
        "str",
        "",
        "Testing: START:STOP:MS sleeps MS ms while processing scans START..STOP-1.",
        hidden=True,
    ),
)
BY_NAME = {p.name: p for p in PARAMS}


def check_value(param: Param, value: Any, where: str) -> Any:
    """``value`` as ``param``'s type, or MsdnetError naming ``where`` (the flag, or the file and key)."""
    from msdnet.runtime.frontends.live.params_file import shown

    kind = param.kind
    ok = {
        "bool": isinstance(value, bool),
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "str": isinstance(value, str),
        "list": isinstance(value, list) and all(isinstance(v, str) for v in value),
    }[kind]
    if not ok:
        want = {"list": "a list of strings", "int": "an integer"}.get(kind, f"a {kind}")
        raise MsdnetError(where, f"expected {want}, got {shown(value)}")
    if kind == "float":
        value = float(value)
        if value != value or value in (float("inf"), float("-inf")):
            raise MsdnetError(where, f"expected a finite number, got {value!r}")
    if param.low is not None and value < param.low:
        raise MsdnetError(where, f"must be >= {param.low:g}, got {shown(value)}")
    if param.high is not None and value > param.high:
        raise MsdnetError(where, f"must be <= {param.high:g}, got {shown(value)}")
    for text in value if kind == "list" else [value] if kind == "str" else []:
        if any(ord(c) < 0x20 or ord(c) == 0x7F for c in text):
            raise MsdnetError(where, f"holds a control character: {shown(text)}")
    if param.choices and value not in param.choices:
        allowed = ", ".join(repr(c) if not c else c for c in param.choices)
        raise MsdnetError(where, f"must be one of {allowed}; got {shown(value)}")
    return list(value) if kind == "list" else value


def fully_qualified(name: str, namespace: str) -> str:
    """``/ns/name``: the node's name in its namespace (ROS 2's fully qualified node name)."""
    return "/" + "/".join(t for t in f"{namespace}/{name}".split("/") if t)


def _identity(
    path: Path, sections: dict[str, dict[str, Any]], flags: dict[str, Any], given: set[str]
) -> tuple[str, str, str | None]:
    """(node name, namespace, the section whose name or namespace is in effect or None), flags first."""
    named_by = None
    out = {"node_name": NODE_NAME, "namespace": "/"}
    for name in out:
        if name in given:
            out[name] = flags[name]
            continue
        for key in ("/**", f"/{NODE_NAME}"):  # where a file may name the node
            if name in sections.get(key, {}):
                out[name] = check_value(BY_NAME[name], sections[key][name], f"{path}: {name}")
                named_by = key if key != "/**" else named_by
    return out["node_name"], out["namespace"], named_by


def file_values(path: Path, flags: dict[str, Any], given: set[str]) -> dict[str, Any]:
    """The node's parameters from the file at ``path`` (module docstring: which sections apply),
    each checked, errors naming the file and key."""
    from msdnet.runtime.frontends.live.params_file import is_pattern, load, matches

    sections = load(path)
    name, namespace, named_by = _identity(path, sections, flags, given)
    fqn = fully_qualified(name, namespace)
    applied = [k for k in sections if is_pattern(k) and matches(k, fqn)]
    applied += [k for k in (named_by,) if k is not None and k != fqn]
    applied += [k for k in sections if not is_pattern(k) and k == fqn]
    if not applied:
        raise MsdnetError(
            path, f"no '{fqn.lstrip('/')}: ros__parameters:' section (sections: {', '.join(sections)})"
        )
    values: dict[str, Any] = {}
    for key in applied:
        for param, value in sections[key].items():
            if param not in BY_NAME:
                known = ", ".join(sorted(BY_NAME))
                raise MsdnetError(path, f"{key}: unknown parameter {param!r} (known: {known})")
            values[param] = check_value(BY_NAME[param], value, f"{path}: {param}")
    for param in ("node_name", "namespace"):
        own = sections.get(fqn, {}).get(param)
        if (
            own is not None
            and fully_qualified(
                own if param == "node_name" else name, own if param == "namespace" else namespace
            )
            != fqn
        ):
            raise MsdnetError(f"{path}: {param}", f"{own!r} differs from the node of section {fqn}")
    return values


def resolve(
    file_values: dict[str, Any], flags: dict[str, Any], given: set[str], path: Path | None = None
) -> tuple[dict[str, Any], dict[str, str]]:
    """Every parameter: the default, then the file, then a flag given on the command line;
    -> (values, origin: where each value came from, as error messages name it: the flag, or
    ``FILE: key``; a default is named by its flag)."""
    values: dict[str, Any] = {}
    origin: dict[str, str] = {}
    for p in PARAMS:
        if p.name in given:
            values[p.name] = check_value(p, flags[p.name], p.flag)
            origin[p.name] = p.flag
        elif p.name in file_values:
            values[p.name] = file_values[p.name]
            origin[p.name] = f"{path}: {p.name}"
        else:
            values[p.name] = list(p.default) if p.kind == "list" else p.default
            origin[p.name] = p.flag
    return values, origin


def dump(values: dict[str, Any]) -> str:
    """The parameters in the ``msdnet_node: ros__parameters:`` form (hidden ones when set); the
    node's name and namespace are parameters there, so the dump read back is the same node."""
    import yaml

    shown = {p.name: values[p.name] for p in PARAMS if not p.hidden or values[p.name] != p.default}
    return yaml.safe_dump({NODE_NAME: {"ros__parameters": shown}}, sort_keys=False)
