"""``msdnet-data show`` (a BEV picture of one preprocessed frame) and ``msdnet-data stats``.

``show`` draws with the ``pictures`` extra and removes the LiDAR's ground with the ``metrics``
extra, both imported when it runs, so ``--help`` needs neither."""

from __future__ import annotations

import click
import numpy as np
from tqdm import tqdm

from msdnet.runtime.errors import one_line_errors, require_extra
from msdnet.runtime.io.atomic import checks_outputs
from msdnet.runtime.io.datasets import DATASET_NAMES, open_dataset
from msdnet.runtime.io.datasets.stats import TARGETS, compute_stats, format_stats
from msdnet.runtime.spec.grid import GRID_PRESETS

DATASET_CHOICE = click.Choice(DATASET_NAMES)
PRESET_CHOICE = click.Choice(sorted(GRID_PRESETS))


@click.command()
@click.option("--dataset", "dataset", type=DATASET_CHOICE, required=True, help="Dataset layout.")
@click.option("--data", "data", required=True, help="Dataset root folder.")
@click.option("--frame", "frame_id", required=True, help="Frame id, e.g. 00549 or 000000.")
@click.option("--out", "out", required=True, help="PNG file to write.")
@click.option("--preset", type=PRESET_CHOICE, default="lite", show_default=True, help="Grid.")
@click.option("--radar-frames", type=click.IntRange(min=1), default=1, show_default=True)
@click.option("--keep-ground", is_flag=True, help="Skip ground removal.")
@one_line_errors
@checks_outputs(out="file")  # before any work
def show(
    dataset: str,
    data: str,
    frame_id: str,
    out: str,
    preset: str,
    radar_frames: int,
    keep_ground: bool,
) -> None:
    """Draw one preprocessed frame from above: radar over LiDAR, grid range outlined."""
    require_extra("matplotlib", "msdnet-data show")
    if not keep_ground:
        require_extra("pypatchworkpp", "ground removal (--keep-ground skips it)")
    from msdnet.runtime.io.datasets.preprocess import lidar_ground, preprocess_frame
    from msdnet.runtime.io.pictures import RADAR_COLOUR, Layer, render_bev

    grid = GRID_PRESETS[preset]
    frame = open_dataset(dataset, data, radar_frames=radar_frames).get(frame_id)
    cropped = preprocess_frame(frame, grid, remove_ground=False)
    lidar = cropped.lidar.xyz
    ground_xyz = np.zeros((0, 3), dtype=np.float32)
    method = "kept"
    if not keep_ground:
        result = lidar_ground(cropped)
        ground_xyz, lidar, method = lidar[result.mask], lidar[~result.mask], result.method
    layers = [
        Layer(ground_xyz, "#d9c9a3", f"LiDAR ground removed ({method})"),
        Layer(lidar, "#555555", "LiDAR"),
        Layer(cropped.radar.xyz, RADAR_COLOUR, "radar", "radar"),
    ]
    title = f"{dataset} {frame_id} ({preset} grid, radar frame)"
    note = "counts: points inside the grid box (LiDAR: and the field of view)"
    path = render_bev(out, layers if not keep_ground else layers[1:], grid, title, note)
    click.echo(
        f"wrote {path}: radar {len(cropped.radar)}/{len(frame.radar)}, "
        f"LiDAR {len(lidar)}/{len(frame.lidar)} (ground: {method})"
    )


@click.command()
@click.option("--dataset", "dataset", type=DATASET_CHOICE, required=True, help="Dataset layout.")
@click.option("--data", "data", required=True, help="Dataset root folder.")
@click.option(
    "--frames",
    "max_frames",
    type=click.IntRange(min=1),
    default=None,
    help="Measure K frames spread evenly over the dataset (default: all).",
)
@click.option("--preset", type=PRESET_CHOICE, default="paper", show_default=True, help="Grid.")
@click.option("--radar-frames", type=click.IntRange(min=1), default=1, show_default=True)
@click.option(
    "--targets",
    type=click.Choice(sorted(TARGETS)),
    default=None,
    help="Bands to judge against: vod or astyx (default: astyx for astyx / sim-astyx, else vod).",
)
@one_line_errors
def stats(
    dataset: str, data: str, max_frames: int | None, preset: str, radar_frames: int, targets: str | None
) -> None:
    """Print a dataset folder's realism statistics: point counts, spread and radar values, each
    against the band measured on real View-of-Delft or Astyx frames."""
    ds = open_dataset(dataset, data, radar_frames=radar_frames)
    n = len(ds) if max_frames is None else min(max_frames, len(ds))
    picks = np.unique(np.linspace(0, len(ds) - 1, n).round().astype(int))
    frames = (ds[int(i)] for i in tqdm(picks, desc="frames", unit="frame", leave=False))
    result = compute_stats(frames, GRID_PRESETS[preset])
    click.echo(f"{dataset} {data}: {result.frames} of {len(ds)} frames, {preset} grid region")
    name = targets or ("astyx" if dataset in ("astyx", "sim-astyx") else "vod")
    click.echo(format_stats(result, TARGETS[name], "VoD" if name == "vod" else "Astyx"))
