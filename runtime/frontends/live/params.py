"""``msdnet-node``'s parameters: one table, the command line and a ROS 2 parameters file.

Every flag is a parameter: ``--stats-every`` is ``stats_every``. ``--params-file node.yaml`` reads
ROS 2's form::

    msdnet_node:            # or /msdnet_node, or /** (every node)
      ros__parameters:
        input_topic: /radar/points
        input_type: radar_scan
        max_allowed_processing_time_ms: 100.0

Sections for other nodes are skipped, as ``ros2 run --params-file`` does. A flag given on the
command line wins over the file. Unknown keys, values of the wrong type and values outside
their range are one-line errors naming the key (and the file). :func:`dump` writes the resolved
parameters back in the same form (``--print-params``), which a ``--params-file`` reproduces.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from msdnet.runtime.errors import MsdnetError

NODE_NAME = "msdnet_node"


@dataclass(frozen=True)
class Param:
    """One parameter: name, type (``bool int float str list``), default, help, allowed values
    (``choices``), lower bound (``low``, numbers), and whether ``--help`` shows it."""

    name: str
    kind: str
    default: Any
    help: str
    choices: tuple[str, ...] = ()
    low: float | None = None
    hidden: bool = False

    @property
    def flag(self) -> str:
        return "--" + FLAG_NAMES.get(self.name, self.name.replace("_", "-"))


FLAG_NAMES = {"input_topic": "topic", "fields": "field"}  # flags not named after their parameter

PARAMS: tuple[Param, ...] = (
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
    Param("domain_id", "int", 0, "DDS domain (ROS_DOMAIN_ID).", low=0),
    Param("model", "str", "", "msdnet-export folder; empty: the bundled model."),
    Param(
        "provider",
        "str",
        "auto",
        "cpu, cpu-shared, auto, auto-bf16, openvino, openvino-bf16, cuda or tensorrt.",
    ),
    Param("threads", "int", 0, "Intra-op threads; 0: onnxruntime's default.", low=0),
    Param(
        "field_preset",
        "str",
        "",
        "PointCloud2 field names of a sensor layout: vod, astyx, ars548 (nebula), ti; empty: by name.",
        choices=("", "vod", "astyx", "ars548", "ti"),
    ),
    Param("fields", "list", [], "Map a model column to an input field: COLUMN=FIELD (repeatable)."),
    Param("steps", "int", 0, "DDIM steps; 0: the manifest's T_m.", low=0),
    Param("threshold", "float", 0.0, "Occupancy threshold in (0, 1); 0: the manifest's.", low=0.0),
    Param("seed", "int", 0, "Noise seed.", low=0),
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
        "max_allowed_processing_time_ms",
        "float",
        100.0,
        "Diagnostics WARN when one scan's processing time is above this.",
        low=0.0,
    ),
    Param(
        "max_acceptable_consecutive_delay_ms",
        "float",
        1000.0,
        "Diagnostics ERROR when processing stays above the limit for longer than this.",
        low=0.0,
    ),
    Param("foxglove", "bool", False, "Serve the radar and dense clouds to Foxglove over WebSocket."),
    Param("foxglove_host", "str", "127.0.0.1", "Address the Foxglove server binds."),
    Param("foxglove_port", "int", 8765, "Foxglove server port; 0: any free port.", low=0),
    Param("stats_every", "int", 0, "Stats line every N messages; 0: only at exit.", low=0),
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
    """``value`` as ``param``'s type, or MsdnetError naming ``where`` (the file and key)."""
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
        raise MsdnetError(where, f"expected {want}, got {value!r}")
    if kind == "float":
        value = float(value)
        if value != value or value in (float("inf"), float("-inf")):
            raise MsdnetError(where, f"expected a finite number, got {value!r}")
    if param.low is not None and value < param.low:
        raise MsdnetError(where, f"must be >= {param.low:g}, got {value!r}")
    if param.choices and value not in param.choices:
        allowed = ", ".join(repr(c) if not c else c for c in param.choices)
        raise MsdnetError(where, f"must be one of {allowed}; got {value!r}")
    return list(value) if kind == "list" else value


def read_file(path: Path) -> dict[str, Any]:
    """The ``msdnet_node: ros__parameters:`` values of a parameters file, checked; one-line errors."""
    import yaml

    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except OSError as err:
        raise MsdnetError(path, f"cannot read: {err.strerror or err}") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        raise MsdnetError(
            path, f"not YAML{at}: {getattr(err, 'problem', None) or type(err).__name__}"
        ) from None
    if not isinstance(doc, dict):
        raise MsdnetError(path, f"expected '{NODE_NAME}: ros__parameters: ...' at the top")
    values: dict[str, Any] = {}
    found = False
    for section in ("/**", f"/{NODE_NAME}", NODE_NAME):  # the node's own section wins, as in ROS 2
        found |= _merge(path, section, doc.get(section), values)
    if not found:
        raise MsdnetError(
            path, f"no '{NODE_NAME}: ros__parameters:' section (keys: {', '.join(map(str, doc))})"
        )
    return values


def _merge(path: Path, section: str, body: Any, values: dict[str, Any]) -> bool:
    if body is None:
        return False
    if not isinstance(body, dict) or set(body) != {"ros__parameters"}:
        keys = ", ".join(map(str, body)) if isinstance(body, dict) else repr(body)
        raise MsdnetError(path, f"{section}: expected only 'ros__parameters:', got {keys}")
    params = body["ros__parameters"] or {}
    if not isinstance(params, dict):
        raise MsdnetError(path, f"{section}.ros__parameters: expected a mapping, got {params!r}")
    for key, value in params.items():
        if key not in BY_NAME:
            raise MsdnetError(path, f"unknown parameter {key!r} (known: {', '.join(sorted(BY_NAME))})")
        values[key] = check_value(BY_NAME[key], value, f"{path}: {key}")
    return True


def resolve(file_values: dict[str, Any], flags: dict[str, Any], given: set[str]) -> dict[str, Any]:
    """Every parameter: the default, then the file, then a flag given on the command line."""
    out: dict[str, Any] = {}
    for p in PARAMS:
        if p.name in given:
            out[p.name] = check_value(p, flags[p.name], p.flag)
        elif p.name in file_values:
            out[p.name] = file_values[p.name]
        else:
            out[p.name] = list(p.default) if p.kind == "list" else p.default
    return out


def dump(values: dict[str, Any]) -> str:
    """The parameters in the ``msdnet_node: ros__parameters:`` form (hidden ones when set)."""
    import yaml

    shown = {p.name: values[p.name] for p in PARAMS if not p.hidden or values[p.name] != p.default}
    return yaml.safe_dump({NODE_NAME: {"ros__parameters": shown}}, sort_keys=False)
