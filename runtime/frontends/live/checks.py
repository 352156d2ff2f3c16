"""``msdnet-node``'s start-up checks of what the parameters mean together, before any scan.

Each is one ``MsdnetError`` line; ``cli.config_from`` names the flag, or the parameters file and
key, the value came from:

- the node's name and namespace are ROS 2 names (:func:`check_identity`); topic names resolve as
  ROS 2 resolves them (:func:`resolve_topic`: ``~/x`` under the node, ``x`` under its namespace);
- the node never reads what it writes: the input topic is none of its own topics (dense cloud,
  ``~/debug/*``, ``/diagnostics``) and the dense cloud goes to none of the others
  (:func:`check_topics`);
- ``fields`` that cannot apply to a RadarScan (:func:`check_radar_scan_fields`);
- an extrinsic that would move the model's points out of float32 (non-finite) or so far that
  float32 can no longer tell voxels apart (:func:`check_extrinsic`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.live.params_file import valid_token

FLOAT32_MAX = float(np.finfo(np.float32).max)


def check_identity(name: str, namespace: str, origin: dict[str, str]) -> tuple[str, str]:
    """(node name, namespace as ``/a/b``) if ROS 2 accepts them; MsdnetError naming the parameter."""
    if not valid_token(name):
        raise MsdnetError(
            origin.get("node_name", "--node-name"),
            f"{name!r} is not a ROS 2 node name (letters, digits and _, not starting with a digit)",
        )
    tokens = namespace.strip("/").split("/") if namespace.strip("/") else []
    trailing = namespace != "/" and namespace.endswith("/")
    if "//" in namespace or trailing or not all(map(valid_token, tokens)):
        raise MsdnetError(
            origin.get("namespace", "--namespace"),
            f"{namespace!r} is not a ROS 2 namespace (e.g. /sensing/radar/front)",
        )
    return name, "/" + "/".join(tokens)


def resolve_topic(name: str, namespace: str, fqn: str) -> str:
    """A ROS 2 topic name as the node resolves it: ``/a/b`` as is, ``~/b`` under the node
    (``fqn``), ``b`` under ``namespace``; MsdnetError for a name ROS 2 refuses."""
    from msdnet.runtime.frontends.live.idl import dds_topic

    if name.startswith("~"):
        full = fqn + name[1:] if name == "~" or name.startswith("~/") else ""
    elif name.startswith("/"):
        full = name
    else:
        full = namespace.rstrip("/") + "/" + name
    if not full or full.endswith("/") or full == "/":
        raise MsdnetError("--topic", f"{name!r} is not a ROS 2 topic name (e.g. /radar/points)")
    try:
        dds_topic(full)
    except MsdnetError:
        raise MsdnetError("--topic", f"{name!r} is not a ROS 2 topic name (e.g. /radar/points)") from None
    return full


def check_topics(cfg: Any, origin: dict[str, str]) -> None:
    """The input topic is none of the node's own topics, and its own topics are all different."""
    from msdnet.runtime.frontends.live.observe import node_topics

    own = node_topics(cfg)
    for what, topic in own.items():
        if topic == cfg.topic:
            where = origin.get("output_topic", "--output-topic") if what == "output_topic" else None
            where = where or origin.get("input_topic", "--topic")
            raise MsdnetError(
                where, f"{topic} is both the input topic and the node's {what}: it would read what it writes"
            )
    dense = own.pop("output_topic")
    for what, topic in own.items():
        if topic == dense:
            raise MsdnetError(
                origin.get("output_topic", "--output-topic"), f"{dense} is already the node's {what} topic"
            )


def check_radar_scan_fields(specs: list[str], columns: tuple[str, ...]) -> None:
    """Every model column takes a RadarScan field (``fields`` first, then the radar_scan preset);
    MsdnetError naming ``--field`` otherwise (checked once at start, not on every scan)."""
    from msdnet.runtime.frontends.live.messages import RADAR_SCAN_COLUMNS, field_mapping
    from msdnet.runtime.io.rosbag import parse_field_map

    picked = field_mapping(RADAR_SCAN_COLUMNS, columns, parse_field_map(specs, columns), "radar_scan")
    for col in columns:
        name = picked.get(col, col)
        if name not in RADAR_SCAN_COLUMNS:
            raise MsdnetError(
                "--field",
                f"a RadarScan has no field {name!r} for model column {col!r} (its fields as the node reads "
                f"them: {' '.join(RADAR_SCAN_COLUMNS)})",
            )


def check_extrinsic(text: str, grid: Any) -> tuple[float, ...]:
    """``x,y,z,roll,pitch,yaw`` -> its six numbers, if every point the model can publish (the
    grid's box) stays finite in float32 and float32 still tells two voxels apart there."""
    from msdnet.runtime.io.pairing.transforms import parse_extrinsic

    transform = parse_extrinsic(text)
    values = tuple(float(v) for v in text.split(","))
    lo, hi = np.asarray(grid.point_range[:3], np.float64), np.asarray(grid.point_range[3:], np.float64)
    corners = np.array([[(hi if (k >> i) & 1 else lo)[i] for i in range(3)] for k in range(8)])
    with np.errstate(over="ignore", invalid="ignore"):
        moved = corners @ transform[:3, :3].T + transform[:3, 3]
        as32 = moved.astype(np.float32)
    if not np.all(np.isfinite(moved)) or not np.all(np.isfinite(as32)):
        raise MsdnetError(
            "--extrinsic", f"{text!r} moves the model's points beyond float32 (their x y z would be infinite)"
        )
    step = float(np.spacing(np.abs(as32).max()))
    if step > min(grid.voxel_size) / 2:
        raise MsdnetError(
            "--extrinsic",
            f"{text!r} moves the model's points so far ({np.abs(moved).max():.3g} m) that float32 holds "
            f"them only {step:.3g} m apart, coarser than the voxels",
        )
    return values
