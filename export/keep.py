"""The keep threshold: which input radar points the decoder keeps as they are.

Each input radar point inside the grid box gets a confidence from the model's own head output
(``runtime.engine.decode.radar_confidence_*``: the largest full-scale occupancy over the
3 x 3 x 3 voxels around it); the runtime appends the points whose confidence reaches the
manifest's ``keep_radar_threshold`` to the model's points (``Pipeline``). Threshold 0 keeps every
radar point (``--keep-radar``); no threshold keeps none (the model's points only).

The threshold is chosen on held-out frames of the training range (the selection slice, never
validation): every candidate is scored with the scene metrics (``runtime.metrics``: CD, MHD,
F@0.2, F@0.5, JSD, means over the frames, clouds cropped like the reference) and the pick is
the candidate with the lowest CD among those at least as good as keeping every radar point on all
five; when none is, the lowest CD (and the manifest says so).

``msdnet-export keep MODEL --dataset astyx --data ROOT --first 000299 --last 000351
[--write]`` prints the table and, with ``--write``, records the pick in MODEL's manifest
(``keep_radar_threshold`` and ``keep_radar_calibration``), rewritten atomically.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from msdnet.export.manifest_fields import update_manifest
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.datasets import FrameDataset, open_dataset
from msdnet.runtime.io.datasets.preprocess import preprocess_frame
from msdnet.runtime.metrics.cloud import scene_scores
from msdnet.runtime.metrics.crop import crop_to_grid, xy_range
from msdnet.runtime.model.artifact import MANIFEST

CANDIDATES = (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5)  # keep thresholds tried by default
# scene metrics the pick compares with keeping every radar point: key -> lower is better
SCENE = {"cd": True, "mhd": True, "fscore@0.2": False, "fscore@0.5": False, "jsd": True}


@dataclass(frozen=True)
class KeepCalibration:
    """The chosen keep threshold and the table it was chosen from."""

    threshold: float  # the pick
    met_keep_all: bool  # the pick is at least as good as keeping every radar point on all of SCENE
    frames: list[str]  # frames scored
    rule: str = "largest full-scale occupancy over the 3x3x3 voxels around the radar point's voxel"
    # candidate -> {SCENE metric: mean, "points": mean points per frame}; "model" (none kept) and
    # "keep all" (threshold 0) as well
    table: dict[str, dict[str, float]] = field(default_factory=dict)


def table_row(rows: list[dict[str, float]], points: list[int]) -> dict[str, float]:
    """Per-frame ``scene_scores`` and point counts -> {SCENE metric: mean over the frames where it
    is finite, "points": mean points per frame}."""

    def mean(values: list[float]) -> float:
        arr = np.asarray(values, dtype=np.float64)
        arr = arr[np.isfinite(arr)]
        return float(arr.mean()) if arr.size else float("nan")

    table = {k: mean([r[k] for r in rows]) for k in SCENE}
    return table | {"points": float(np.mean(points)) if points else float("nan")}


def slice_ids(ds: FrameDataset, data: Path, first: str, last: str) -> list[str]:
    """The frame ids FIRST..LAST of ``ds`` (ids of FIRST's length); a one-line error when none."""
    ids = [f for f in ds.frame_ids if first <= f <= last and len(f) == len(first)]
    if not ids:
        raise MsdnetError(data, f"has no frames {first}..{last}")
    return ids


def at_least_as_good(row: dict[str, float], base: dict[str, float]) -> bool:
    """Whether ``row`` is at least as good as ``base`` on every ``SCENE`` metric."""
    return all(row[k] <= base[k] if low else row[k] >= base[k] for k, low in SCENE.items())


def calibrate_keep(
    pipe: Pipeline,
    ds: FrameDataset,
    frame_ids: list[str],
    candidates: tuple[float, ...] = CANDIDATES,
    seed: int = 0,
    progress: bool = True,
) -> KeepCalibration:
    """Score the model's points plus the radar points kept at each candidate on ``frame_ids``
    (one model run per frame: the radar points' confidences are the same at every candidate) and
    pick the threshold (module docstring)."""
    if not candidates or min(candidates) <= 0.0 or max(candidates) > 1.0:
        raise MsdnetError("--candidates", f"need thresholds in (0, 1], got {candidates}")
    grid = pipe.artifact.grid
    area = xy_range(grid)
    names = ["model", "keep all", *(f"{t:g}" for t in candidates)]
    scores: dict[str, list[dict[str, float]]] = {n: [] for n in names}
    points: dict[str, list[int]] = {n: [] for n in names}
    for fid in tqdm(frame_ids, desc="keep threshold", unit="frame", disable=not progress or None):
        frame = preprocess_frame(ds.get(fid), grid)
        ref = crop_to_grid(frame.lidar.xyz, grid)
        res = pipe(frame.radar, seed=seed, keep_threshold=0.0)  # every radar row, with its confidence
        conf = res.radar_confidence if res.radar_confidence is not None else np.zeros(0, np.float32)
        model = res.points[: len(res.points) - len(conf)]
        radar = res.points[len(model) :]
        for name in names:
            if name == "model":
                pred = model
            elif name == "keep all":
                pred = res.points
            else:
                pred = np.concatenate([model, radar[conf >= np.float32(float(name))]])
            pred = crop_to_grid(pred, grid)
            scores[name].append(scene_scores(pred, ref, area))
            points[name].append(len(pred))
    table = {n: table_row(scores[n], points[n]) for n in names}
    base = table["keep all"]
    passing = [t for t in candidates if at_least_as_good(table[f"{t:g}"], base)]
    pool = passing or list(candidates)
    pick = min(pool, key=lambda t: (table[f"{t:g}"]["cd"], t))
    return KeepCalibration(float(pick), bool(passing), list(frame_ids), table=table)


def write_keep(folder: Path, cal: KeepCalibration, split: str) -> None:
    """Record ``cal`` in ``folder``'s manifest (``keep_radar_threshold``, ``keep_radar_calibration``),
    atomically. Only manifest.json changes; a signature over it must be made again."""
    fields = {"keep_radar_threshold": cal.threshold, "keep_radar_calibration": asdict(cal) | {"split": split}}
    update_manifest(folder, fields)


def calibration_markdown(cal: KeepCalibration) -> str:
    """The candidate table as Markdown (one row per candidate; the pick marked)."""
    lines = [
        "| keep threshold | CD (m) | MHD (m) | F@0.2 | F@0.5 | JSD | points / frame "
        "| ≥ keep all on all five |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    base = cal.table["keep all"]
    for name, r in cal.table.items():
        mark = " (pick)" if name not in ("model", "keep all") and float(name) == cal.threshold else ""
        ok = "–" if name in ("model", "keep all") else ("yes" if at_least_as_good(r, base) else "no")
        lines.append(
            f"| {name}{mark} | {r['cd']:.4f} | {r['mhd']:.4f} | {r['fscore@0.2']:.4f} | "
            f"{r['fscore@0.5']:.4f} | {r['jsd']:.4f} | {r['points']:.0f} | {ok} |"
        )
    return "\n".join(lines) + "\n"


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("model", type=click.Path(path_type=Path))
@click.option("--dataset", required=True, help="Dataset name of --data (astyx, vod, sim, sim-astyx).")
@click.option("--data", type=click.Path(path_type=Path), required=True, help="Dataset root.")
@click.option("--first", required=True, help="First frame id of the selection slice (e.g. 000299).")
@click.option("--last", required=True, help="Last frame id of the selection slice (e.g. 000351).")
@click.option(
    "--candidates",
    default=",".join(f"{t:g}" for t in CANDIDATES),
    show_default=True,
    help="Keep thresholds tried, comma-separated, each in (0, 1].",
)
@click.option("--write", is_flag=True, help="Record the pick in MODEL's manifest.")
@click.option("--seed", type=int, default=0, show_default=True, help="Diffusion noise seed.")
@one_line_errors
def main(
    model: Path, dataset: str, data: Path, first: str, last: str, candidates: str, write: bool, seed: int
) -> None:
    """Choose MODEL's keep threshold on the selection slice FIRST..LAST (never validation)."""
    try:
        cands = tuple(float(v) for v in candidates.split(",") if v.strip())
    except ValueError:
        raise MsdnetError("--candidates", f"expected comma-separated numbers, got {candidates!r}") from None
    ds = open_dataset(dataset, data)
    ids = slice_ids(ds, data, first, last)
    pipe = Pipeline.from_dir(model)
    cal = calibrate_keep(pipe, ds, ids, cands, seed)
    click.echo(calibration_markdown(cal), nl=False)
    verdict = "at least as good as keeping every radar point" if cal.met_keep_all else "lowest CD (none"
    verdict += "" if cal.met_keep_all else " is at least as good as keeping every radar point)"
    click.echo(f"pick: {cal.threshold:g} on {len(ids)} frames {first}..{last} ({verdict})")
    if write:
        write_keep(model, cal, f"selection slice {first}..{last}")
        click.echo(f"{model}/{MANIFEST}: keep_radar_threshold {cal.threshold:g}")
