"""Pair the radar and LiDAR messages of a ROS bag by stamp and write the VoD layout.

Each radar scan takes the LiDAR sweep nearest in header stamp; a scan with none within
``max_skew`` seconds is dropped (and so is a scan that cannot be read), each with the reason in
the report. The radar-to-LiDAR transform comes from ``--extrinsic`` or ``/tf_static`` (the chain
between the two messages' frame ids). Output (``runtime/io/datasets/vod`` reads it; frame ids
``00000``, ``00001``, ... in stamp order)::

    OUT/radar/training/velodyne/<id>.bin   float32 x y z rcs v_r v_r_compensated time
    OUT/radar/training/calib/<id>.txt      Tr_velo_to_cam = T_lidar<-radar (the "camera" is the LiDAR)
    OUT/lidar/training/velodyne/<id>.bin   float32 x y z intensity (LiDAR frame)
    OUT/lidar/training/calib/<id>.txt      Tr_velo_to_cam = identity
    OUT/lidar/training/pose/<id>.json      odomToCamera = T_odom<-lidar, when /tf or odometry has it
    OUT/lidar/ImageSets/{train,val}.txt    split by contiguous ranges (split_contiguous)

Radar columns the messages lack (after ``--field`` mapping) are written as 0 and named in the
report. OUT's place is checked writable before the bag is read, and the folder is written under
a temporary name next to OUT and renamed when complete (``io.atomic.atomic_folder``); a killed
run's temporary folder is removed by the next run (``io.atomic.check_writable``).
"""

from __future__ import annotations

import bisect
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msdnet.runtime.engine.pointcloud import canonical_column
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.atomic import atomic_folder, check_writable
from msdnet.runtime.io.datasets.frame import split_contiguous
from msdnet.runtime.io.files import LIDAR_COLUMNS, VOD_RADAR_COLUMNS
from msdnet.runtime.io.pairing.transforms import TfTree, matrix, stamp_ns
from msdnet.runtime.io.rosbag import (
    POINTCLOUD2,
    POINTFIELD_TYPES,
    _rosbags,
    parse_field_map,
    pointcloud2_to_array,
)

TF_TYPE = "tf2_msgs/msg/TFMessage"
ODOM_TYPE = "nav_msgs/msg/Odometry"
LIDAR_ALIASES = {"intensity": ("intensity", "reflectance", "reflectivity", "i")}  # first found wins
VAL_FRACTION = 0.2  # share of frames in ImageSets/val.txt (the last contiguous range)


@dataclass(frozen=True)
class PairOptions:
    """What ``msdnet-data pair`` reads and how it pairs."""

    radar_topic: str  # PointCloud2 topic of the radar
    lidar_topic: str  # PointCloud2 topic of the LiDAR
    max_skew: float = 0.05  # seconds: a radar scan takes the nearest LiDAR sweep within this
    extrinsic: np.ndarray | None = None  # (4, 4) T_lidar<-radar; None: from /tf_static
    radar_fields: tuple[str, ...] = ()  # --field column=msg_field for the radar columns
    odom_topic: str | None = None  # nav_msgs/Odometry topic for poses; None: /tf, else any odometry


@dataclass
class PairReport:
    """What was written and what was dropped (with why)."""

    pairs: int = 0  # frame pairs written
    dropped: list[str] = field(default_factory=list)  # "radar message i at t: why"
    notes: list[str] = field(default_factory=list)  # e.g. zero-filled columns, pose source
    poses: int = 0  # frames with a pose file

    def lines(self, out: Path) -> list[str]:
        text = [
            f"wrote {self.pairs} frame pairs to {out} ({self.poses} with poses); dropped {len(self.dropped)}"
        ]
        return text + [f"  note: {n}" for n in self.notes] + [f"  dropped: {d}" for d in self.dropped]


def _field(msg: Any, names: Sequence[str]) -> Any:
    by_name = {f.name: f for f in msg.fields}
    by_canon = {canonical_column(f.name): f for f in msg.fields}
    for name in names:
        f = by_name.get(name) or by_canon.get(canonical_column(name))
        if f is not None and f.count == 1 and f.datatype in POINTFIELD_TYPES:
            return f
    return None


def read_columns(
    msg: Any, columns: Sequence[str], aliases: dict[str, Sequence[str]]
) -> tuple[np.ndarray, list[str]]:
    """PointCloud2 -> (N, len(columns)) float32 in ``columns`` order, a column with no field
    written as 0; -> (values, names of the zero-filled columns). ValueError without x y z."""
    found = {c: _field(msg, aliases.get(c, (c,))) for c in columns}
    missing = [c for c, f in found.items() if f is None]
    if any(c in missing for c in ("x", "y", "z")):
        raise ValueError(f"no float field for {', '.join(c for c in 'xyz' if c in missing)}")
    have = [c for c in columns if c not in missing]
    values = pointcloud2_to_array(msg, [found[c] for c in have])
    out = np.zeros((values.shape[0], len(columns)), np.float32)
    for i, c in enumerate(have):
        out[:, columns.index(c)] = values[:, i]
    return out, missing


def _write_calib(path: Path, t: np.ndarray) -> None:
    path.write_text(
        "Tr_velo_to_cam: " + " ".join(f"{v:.17g}" for v in t[:3].reshape(-1)) + "\n", encoding="utf-8"
    )


def _scan_bag(reader: Any, opts: PairOptions) -> tuple[list[int], list[int], TfTree, str | None, str | None]:
    """Pass 1: radar and LiDAR header stamps (message order), the TF tree, the two frame ids."""
    tree, radar, lidar, frames = TfTree(), [], [], {"radar": None, "lidar": None}
    topics = {opts.radar_topic: "radar", opts.lidar_topic: "lidar"}
    odom = opts.odom_topic
    if odom is None and "/tf" not in reader.topics:
        odom = next((t for t, i in reader.topics.items() if i.msgtype == ODOM_TYPE), None)
    wanted = [c for c in reader.connections if c.topic in (*topics, "/tf", "/tf_static", odom)]
    for conn, _, raw in tqdm(
        reader.messages(connections=wanted), desc="msdnet-data pair: scan", unit="msg", disable=None
    ):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.topic in topics:
            side = topics[conn.topic]
            (radar if side == "radar" else lidar).append(stamp_ns(msg.header))
            frames[side] = frames[side] or msg.header.frame_id.lstrip("/")
        elif conn.topic in ("/tf", "/tf_static"):
            tree.add_message(msg, conn.topic == "/tf_static")
        elif conn.msgtype == ODOM_TYPE:
            p = msg.pose.pose
            mat = matrix(
                (p.position.x, p.position.y, p.position.z),
                (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w),
            )
            tree.add_timed(msg.header.frame_id, msg.child_frame_id, stamp_ns(msg.header), mat)
    return radar, lidar, tree, frames["radar"], frames["lidar"]


def pair_stamps(
    radar: Sequence[int], lidar: Sequence[int], max_skew_ns: int
) -> tuple[dict[int, int], dict[int, str]]:
    """Nearest LiDAR stamp per radar stamp -> ({radar index: lidar index}, {radar index: why dropped})."""
    order = sorted(range(len(lidar)), key=lambda j: lidar[j])
    sorted_stamps = [lidar[j] for j in order]
    pairs, dropped = {}, {}
    for i, t in enumerate(radar):
        k = bisect.bisect_left(sorted_stamps, t)
        near = [c for c in (k - 1, k) if 0 <= c < len(order)]
        if not near:
            dropped[i] = "the bag has no LiDAR sweep"
            continue
        best = min(near, key=lambda c: abs(sorted_stamps[c] - t))
        skew = abs(sorted_stamps[best] - t)
        if skew > max_skew_ns:
            dropped[i] = f"no LiDAR sweep within {max_skew_ns / 1e6:g} ms (nearest {skew / 1e6:.1f} ms away)"
        else:
            pairs[i] = order[best]
    return pairs, dropped


def pair_bag(bag: Path, out: Path, opts: PairOptions, echo: Callable[[str], None] = print) -> PairReport:
    """Pair ``bag`` into the VoD layout at ``out`` (module docstring); -> the report."""
    highlevel, _, typesys = _rosbags()
    if out.exists():
        raise MsdnetError(out, "already exists; remove it or choose another --out")
    check_writable(out, "folder")  # before any work; a killed run's temporary folder there is removed
    if not (bag.is_file() and bag.suffix == ".bag") and not (
        bag.is_dir() and (bag / "metadata.yaml").is_file()
    ):
        raise MsdnetError(bag, "not a ROS 1 bag (.bag file) or a ROS 2 bag (folder with metadata.yaml)")
    mapping = parse_field_map(opts.radar_fields, VOD_RADAR_COLUMNS)
    try:
        reader = highlevel.AnyReader(
            [bag], default_typestore=typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
        )
        reader.open()
    except Exception as err:
        raise MsdnetError(bag, f"unreadable bag: {' '.join(str(err).split())[:200]}") from None
    try:
        for topic in (opts.radar_topic, opts.lidar_topic):
            info = reader.topics.get(topic)
            if info is None:
                have = ", ".join(f"{t} ({i.msgtype})" for t, i in reader.topics.items()) or "none"
                raise MsdnetError(bag, f"no topic {topic!r} (topics: {have})")
            if info.msgtype != POINTCLOUD2:
                raise MsdnetError(topic, f"messages are {info.msgtype}, not {POINTCLOUD2}")
        return _pair(reader, bag, out, opts, mapping, echo)
    finally:
        reader.close()


def _pair(
    reader: Any, bag: Path, out: Path, opts: PairOptions, mapping: dict[str, str], echo: Callable[[str], None]
) -> PairReport:
    radar, lidar, tree, radar_frame, lidar_frame = _scan_bag(reader, opts)
    if not radar or not lidar:
        raise MsdnetError(bag, f"no messages on {opts.radar_topic if not radar else opts.lidar_topic}")
    extrinsic = opts.extrinsic
    if extrinsic is None:
        extrinsic = tree.between(lidar_frame, radar_frame)
        if extrinsic is None:
            raise MsdnetError(
                bag,
                f"no /tf_static chain from {radar_frame!r} to {lidar_frame!r}; "
                "pass --extrinsic x,y,z,roll,pitch,yaw",
            )
    report = PairReport()
    skew = round(opts.max_skew * 1e9)
    pairs, dropped = pair_stamps(radar, lidar, skew)
    ids = {i: n for n, i in enumerate(sorted(pairs, key=lambda i: radar[i]))}
    lidar_to_ids: dict[int, list[int]] = {}
    for i, j in pairs.items():
        lidar_to_ids.setdefault(j, []).append(ids[i])
    with atomic_folder(out) as tmp:
        dirs = {
            k: tmp / s / "training" / d
            for k, (s, d) in {
                "rv": ("radar", "velodyne"),
                "rc": ("radar", "calib"),
                "lv": ("lidar", "velodyne"),
                "lc": ("lidar", "calib"),
                "lp": ("lidar", "pose"),
            }.items()
        }
        for d in dirs.values():
            d.mkdir(parents=True)
        failed = _write_frames(
            reader, opts, radar, lidar, ids, lidar_to_ids, mapping, dirs, extrinsic, report
        )
        dropped.update(failed)
        for i in sorted(failed):  # a radar scan that could not be read: its frame is removed
            for d in ("rv", "rc", "lv", "lc", "lp"):
                for p in dirs[d].glob(f"{ids[i]:05d}.*"):
                    p.unlink()
        written = sorted(p.stem for p in dirs["rv"].glob("*.bin"))
        if not written:
            raise MsdnetError(
                bag,
                f"no frame pairs ({len(dropped)} radar scans dropped; "
                f"first: {next(iter(dropped.values()), '')})",
            )
        report.poses = _write_poses(tree, lidar_frame, lidar, pairs, ids, written, dirs["lp"], skew, report)
        train, val = split_contiguous(written, VAL_FRACTION)
        (tmp / "lidar" / "ImageSets").mkdir()
        for name, part in (("train", train), ("val", val), ("full", written)):
            (tmp / "lidar" / "ImageSets" / f"{name}.txt").write_text(
                "".join(f"{i}\n" for i in part), encoding="utf-8"
            )
        report.pairs = len(written)
        report.dropped = [f"radar message {i} at {radar[i]} ns: {why}" for i, why in sorted(dropped.items())]
    return report


def _write_frames(
    reader: Any,
    opts: PairOptions,
    radar: list[int],
    lidar: list[int],
    ids: dict[int, int],
    lidar_to_ids: dict[int, list[int]],
    mapping: dict[str, str],
    dirs: dict[str, Path],
    extrinsic: np.ndarray,
    report: PairReport,
) -> dict[int, str]:
    """Pass 2: write every paired radar scan and LiDAR sweep; -> {radar index: why it failed}."""
    conns = [c for c in reader.connections if c.topic in (opts.radar_topic, opts.lidar_topic)]
    radar_aliases = {c: (mapping[c],) for c in mapping}
    zero_filled: set[str] = set()
    failed: dict[int, str] = {}
    counts = {opts.radar_topic: 0, opts.lidar_topic: 0}
    nonfinite = {"radar": 0, "LiDAR": 0}  # rows with NaN/Inf dropped, counted in a note
    total = len(ids) + sum(len(v) for v in lidar_to_ids.values())
    bar = tqdm(total=total, desc="msdnet-data pair: write", unit="file", disable=None)
    for conn, _, raw in reader.messages(connections=conns):
        index = counts[conn.topic]
        counts[conn.topic] += 1
        is_radar = conn.topic == opts.radar_topic
        targets = (
            [ids[index]] if is_radar and index in ids else [] if is_radar else lidar_to_ids.get(index, [])
        )
        if not targets:
            continue
        try:
            msg = reader.deserialize(raw, POINTCLOUD2)
            if is_radar:
                values, missing = read_columns(msg, VOD_RADAR_COLUMNS, radar_aliases)
                zero_filled.update(missing)
            else:
                values, missing = read_columns(msg, LIDAR_COLUMNS, LIDAR_ALIASES)
        except Exception as err:
            cause = f"unreadable: {' '.join(str(err).split())[:160]}"
            if is_radar:
                failed[index] = cause
            else:  # every radar scan paired with this sweep fails with it
                failed.update(
                    {i: f"its LiDAR sweep {index} is {cause}" for i, n in ids.items() if n in targets}
                )
            continue
        finite = np.isfinite(values).all(axis=1)
        if not finite.all():
            nonfinite["radar" if is_radar else "LiDAR"] += int(finite.size - finite.sum()) * len(targets)
            values = values[finite]
        for n in targets:
            side = "r" if is_radar else "l"
            np.ascontiguousarray(values, dtype="<f4").tofile(dirs[f"{side}v"] / f"{n:05d}.bin")
            _write_calib(dirs[f"{side}c"] / f"{n:05d}.txt", extrinsic if is_radar else np.eye(4))
            bar.update()
    bar.close()
    if any(nonfinite.values()):
        report.notes.append(
            "rows with NaN/Inf dropped: " + ", ".join(f"{n} {side}" for side, n in nonfinite.items() if n)
        )
    if zero_filled:
        names = " ".join(c for c in VOD_RADAR_COLUMNS if c in zero_filled)
        report.notes.append(
            f"radar columns not in the messages, written as 0: {names} (map one with --field)"
        )
    return failed


def _write_poses(
    tree: TfTree,
    lidar_frame: str,
    lidar: list[int],
    pairs: dict[int, int],
    ids: dict[int, int],
    written: list[str],
    folder: Path,
    skew: int,
    report: PairReport,
) -> int:
    """``odomToCamera`` = T_odom<-lidar at each frame's LiDAR stamp, where /tf or odometry has it."""
    by_id = {ids[i]: lidar[j] for i, j in pairs.items()}
    count = 0
    for fid in written:
        pose = tree.pose(lidar_frame, by_id[int(fid)], skew)
        if pose is None:
            continue
        (folder / f"{fid}.json").write_text(json.dumps({"odomToCamera": pose.reshape(-1).tolist()}) + "\n")
        count += 1
    if count == 0:
        folder.rmdir()
        report.notes.append(f"no poses: neither /tf nor an odometry topic places {lidar_frame!r} in time")
    return count
