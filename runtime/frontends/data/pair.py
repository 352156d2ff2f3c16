"""``msdnet-data pair BAG --radar-topic T --lidar-topic T --out DIR`` (``runtime/io/pairing/pair``)."""

from __future__ import annotations

from pathlib import Path

import click

from msdnet.runtime.errors import MsdnetError, one_line_errors, require_extra
from msdnet.runtime.io.atomic import checks_outputs


@click.command("pair", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("bag", type=click.Path(path_type=Path))
@click.option("--radar-topic", required=True, help="Radar PointCloud2 topic.")
@click.option("--lidar-topic", required=True, help="LiDAR PointCloud2 topic.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="New VoD-layout folder.")
@click.option("--max-skew", type=click.FloatRange(min=0.0), default=0.05, show_default=True, help="Seconds.")
@click.option(
    "--extrinsic", metavar="X,Y,Z,ROLL,PITCH,YAW", help="Radar pose in the LiDAR frame [/tf_static]."
)
@click.option(
    "--field", "fields", multiple=True, metavar="COLUMN=FIELD", help="Map a radar column to a field."
)
@click.option("--odom-topic", help="nav_msgs/Odometry topic for poses [/tf, else any odometry topic].")
@one_line_errors
@checks_outputs(out="folder")  # before any work
def pair(
    bag: Path,
    radar_topic: str,
    lidar_topic: str,
    out: Path,
    max_skew: float,
    extrinsic: str | None,
    fields: tuple[str, ...],
    odom_topic: str | None,
) -> None:
    """Pair a bag's radar and LiDAR scans by stamp into a VoD-layout training folder."""
    for package in ("rosbags", "scipy"):  # bags, and poses between stamps
        require_extra(package, "msdnet-data pair", "ros")
    from msdnet.runtime.io.pairing.pair import PairOptions, pair_bag
    from msdnet.runtime.io.pairing.transforms import parse_extrinsic

    if radar_topic == lidar_topic:
        raise MsdnetError("--lidar-topic", "must differ from --radar-topic")
    ext = None if extrinsic is None else parse_extrinsic(extrinsic)
    opts = PairOptions(radar_topic, lidar_topic, max_skew, ext, fields, odom_topic)
    report = pair_bag(bag, out, opts, click.echo)
    click.echo("\n".join(report.lines(out)))
