"""Decoding thresholds by range band: which occupancy threshold each band of range decodes at.

One threshold decodes too few points near the sensor and too many far away (``runtime.spec.
range_threshold``). This command chooses one per band on held-out frames of the training range
(the selection slice, never validation): each frame runs once at the lowest candidate, with the
model's keep rule as in its manifest; every combination of the per-band candidates is then scored
with the scene metrics (CD, MHD, F@0.2, F@0.5, JSD, means over the frames, clouds cropped like the
reference), and the pick is the combination with the lowest CD among those at least as good as the
manifest's single threshold on all five; when none is, the manifest keeps its single threshold.

``msdnet-export bands MODEL --dataset astyx --data ROOT --first 000299 --last 000351
[--write]`` prints the table and, with ``--write``, records the pick in MODEL's manifest
(``range_thresholds`` and ``range_thresholds_calibration``), rewritten atomically. Run it before
``export.keep``: the keep rule is then chosen on the output the runtime gives.
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import click
import numpy as np
from tqdm import tqdm

from msdnet.export.keep import at_least_as_good, slice_ids, table_row
from msdnet.export.manifest_fields import update_manifest
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.datasets import FrameDataset, open_dataset
from msdnet.runtime.io.datasets.preprocess import preprocess_frame
from msdnet.runtime.metrics.cloud import scene_scores
from msdnet.runtime.metrics.crop import crop_to_grid, xy_range
from msdnet.runtime.model.artifact import MANIFEST
from msdnet.runtime.spec.range_threshold import RangeThresholds

EDGES = (10.0, 20.0)  # band edges, metres of horizontal range (the object table's bands)
CANDIDATES = ((0.25, 0.3, 0.35, 0.4), (0.35, 0.4, 0.45), (0.4, 0.45, 0.5, 0.55))  # per band


@dataclass(frozen=True)
class BandCalibration:
    """The chosen range thresholds and the table they were chosen from."""

    edges_m: list[float]  # band edges, metres
    thresholds: list[float] | None  # the pick, one per band; None: keep the single threshold
    single: float  # the manifest's single threshold, the reference
    frames: list[str]  # frames scored
    # "single" and each combination "t0/t1/t2" -> {SCENE metric: mean, "points": mean per frame}
    table: dict[str, dict[str, float]] = field(default_factory=dict)


def _name(ts: tuple[float, ...]) -> str:
    return "/".join(f"{t:g}" for t in ts)


def calibrate_bands(
    pipe: Pipeline,
    ds: FrameDataset,
    frame_ids: list[str],
    edges: tuple[float, ...] = EDGES,
    candidates: tuple[tuple[float, ...], ...] = CANDIDATES,
    seed: int = 0,
    progress: bool = True,
) -> BandCalibration:
    """Score every combination of ``candidates`` (one tuple per band) on ``frame_ids`` and pick
    (module docstring). One model run per frame: a voxel's occupancy does not depend on the
    threshold, so each combination is a filter of the run at the lowest candidate."""
    if len(candidates) != len(edges) + 1 or any(not c for c in candidates):
        raise MsdnetError("--candidates", f"need one non-empty list per band ({len(edges) + 1})")
    single = pipe.artifact.threshold
    lowest = min(single, *(min(c) for c in candidates))
    grid = pipe.artifact.grid
    area = xy_range(grid)
    combos = [RangeThresholds(tuple(edges), ts) for ts in itertools.product(*candidates)]
    runs = []
    for fid in tqdm(frame_ids, desc="range thresholds", unit="frame", disable=not progress or None):
        frame = preprocess_frame(ds.get(fid), grid)
        res = pipe(frame.radar, seed=seed, threshold=lowest)  # one threshold: no bands here
        n_model = len(res.points) - res.stats.get("radar_kept", 0)  # the kept radar rows follow
        model = (res.points[:n_model], res.confidence[:n_model], res.points[n_model:])
        runs.append((model, crop_to_grid(frame.lidar.xyz, grid)))
    table: dict[str, dict[str, float]] = {}
    for name, keep_of in [("single", None), *((_name(c.thresholds), c) for c in combos)]:
        rows, points = [], []
        for (pts, conf, radar), ref in runs:
            keep = conf > np.float32(single) if keep_of is None else keep_of.keep(pts, conf)
            pred = crop_to_grid(np.concatenate([pts[keep], radar]), grid)
            rows.append(scene_scores(pred, ref, area))
            points.append(len(pred))
        table[name] = table_row(rows, points)
    passing = [c for c in combos if at_least_as_good(table[_name(c.thresholds)], table["single"])]
    pick = min(passing, key=lambda c: table[_name(c.thresholds)]["cd"], default=None)
    return BandCalibration(
        list(edges), None if pick is None else list(pick.thresholds), single, list(frame_ids), table
    )


def write_bands(folder: Path, cal: BandCalibration, split: str) -> None:
    """Record ``cal`` in ``folder``'s manifest atomically (no pick: the field is removed). Only
    manifest.json changes; a signature over it must be made again."""
    fields: dict[str, Any] = {"range_thresholds_calibration": asdict(cal) | {"split": split}}
    if cal.thresholds is not None:
        fields["range_thresholds"] = {"edges_m": cal.edges_m, "thresholds": cal.thresholds}
    update_manifest(folder, fields, drop=("range_thresholds",))


def calibration_markdown(cal: BandCalibration, top: int = 10) -> str:
    """The reference and the ``top`` lowest-CD combinations as Markdown (the pick marked)."""
    bands = " / ".join(
        f"{lo:g}–{hi:g} m" for lo, hi in zip([0.0, *cal.edges_m], [*cal.edges_m, float("inf")], strict=True)
    )
    lines = [
        f"| thresholds ({bands}) | CD (m) | MHD (m) | F@0.2 | F@0.5 | JSD | points / frame "
        "| ≥ single on all five |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    ref = cal.table["single"]
    combos = sorted((n for n in cal.table if n != "single"), key=lambda n: cal.table[n]["cd"])[:top]
    pick = None if cal.thresholds is None else _name(tuple(cal.thresholds))
    for name in ["single", *combos]:
        r = cal.table[name]
        label = (
            f"{cal.single:g} everywhere" if name == "single" else name + (" (pick)" if name == pick else "")
        )
        ok = "–" if name == "single" else ("yes" if at_least_as_good(r, ref) else "no")
        lines.append(
            f"| {label} | {r['cd']:.4f} | {r['mhd']:.4f} | {r['fscore@0.2']:.4f} | "
            f"{r['fscore@0.5']:.4f} | {r['jsd']:.4f} | {r['points']:.0f} | {ok} |"
        )
    return "\n".join(lines) + "\n"


def _floats(text: str, what: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise MsdnetError(what, f"expected comma-separated numbers, got {text!r}") from None


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("model", type=click.Path(path_type=Path))
@click.option("--dataset", required=True, help="Dataset name of --data (astyx, vod, sim, sim-astyx).")
@click.option("--data", type=click.Path(path_type=Path), required=True, help="Dataset root.")
@click.option("--first", required=True, help="First frame id of the selection slice (e.g. 000299).")
@click.option("--last", required=True, help="Last frame id of the selection slice (e.g. 000351).")
@click.option("--edges", default=",".join(f"{e:g}" for e in EDGES), show_default=True, help="Band edges, m.")
@click.option(
    "--candidates",
    default=";".join(",".join(f"{t:g}" for t in c) for c in CANDIDATES),
    show_default=True,
    help="Thresholds tried per band: comma-separated, bands separated by ';'.",
)
@click.option("--write", is_flag=True, help="Record the pick in MODEL's manifest.")
@click.option("--seed", type=int, default=0, show_default=True, help="Diffusion noise seed.")
@one_line_errors
def main(
    model: Path,
    dataset: str,
    data: Path,
    first: str,
    last: str,
    edges: str,
    candidates: str,
    write: bool,
    seed: int,
) -> None:
    """Choose MODEL's decoding thresholds by range band on the selection slice FIRST..LAST."""
    cands = tuple(_floats(part, "--candidates") for part in candidates.split(";"))
    if any(not 0.0 < t < 1.0 for c in cands for t in c):
        raise MsdnetError("--candidates", f"thresholds must be in (0, 1), got {candidates!r}")
    edge_m = _floats(edges, "--edges")
    if len(cands) != len(edge_m) + 1 or any(not c for c in cands):
        raise MsdnetError(
            "--candidates", f"need one non-empty list per band ({len(edge_m) + 1}), got {candidates!r}"
        )
    try:
        RangeThresholds(edge_m, tuple(min(c) for c in cands))
    except ValueError as err:
        raise MsdnetError("--edges", str(err)) from None
    ds = open_dataset(dataset, data)
    ids = slice_ids(ds, data, first, last)
    pipe = Pipeline.from_dir(model)
    cal = calibrate_bands(pipe, ds, ids, edge_m, cands, seed)
    click.echo(calibration_markdown(cal), nl=False)
    if cal.thresholds is None:
        click.echo(f"no combination is at least as good as {cal.single:g} everywhere on {len(ids)} frames")
    else:
        click.echo(f"pick: {_name(tuple(cal.thresholds))} on {len(ids)} frames {first}..{last}")
    if write:
        write_bands(model, cal, f"selection slice {first}..{last}")
        click.echo(f"{model}/{MANIFEST}: range_thresholds {cal.thresholds}")
