"""``msdnet-data simulate``: paired LiDAR / 4D-radar sequences in the VoD layout."""

from __future__ import annotations

import time
from pathlib import Path

import click
from tqdm import tqdm

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import checks_outputs
from msdnet.runtime.sim.rigs import SIM_RIGS
from msdnet.runtime.sim.sequence import SequenceSim
from msdnet.runtime.sim.trajectory import FRAME_DT, loop_closures
from msdnet.runtime.sim.writer import (
    VodWriter,
    check_capacity,
    frame_id,
    id_stride,
    prepare_output,
)

FORMAT_VERSION = 1  # of sequences.json


def _splits(n_sequences: int, ids: list[list[str]]) -> tuple[list[str], list[str]]:
    """Contiguous train / val: the last fifth of the sequences (at least one) is val; with one
    sequence, its last fifth of frames."""
    if n_sequences >= 2:
        n_val = max(1, n_sequences // 5)
        train = [i for seq in ids[: n_sequences - n_val] for i in seq]
        val = [i for seq in ids[n_sequences - n_val :] for i in seq]
        return train, val
    frames = ids[0]
    n_val = len(frames) // 5
    return frames[: len(frames) - n_val], frames[len(frames) - n_val :]


def simulate_dataset(
    out: str | Path,
    sequences: int,
    frames: int,
    seed: int,
    overwrite: bool = False,
    progress: bool = True,
    rig: str = "vod",
) -> dict:
    """Simulate ``sequences`` x ``frames`` paired frames into ``out`` (VoD layout, see writer.py)
    on the rig named ``rig`` (``rigs.SIM_RIGS``: ``vod`` or ``astyx``).

    Returns the sequences.json document (with a ``rig`` key unless the rig is ``vod``, whose
    files stay as they were before rigs existed). Raises MsdnetError on bad arguments or a
    non-empty ``out`` without ``overwrite``.
    """
    if rig not in SIM_RIGS:
        raise MsdnetError(None, f"unknown rig {rig!r} (choose from {', '.join(SIM_RIGS)})")
    sim_rig = SIM_RIGS[rig]
    if sequences < 1 or frames < 1:
        raise MsdnetError(None, f"need at least 1 sequence and 1 frame, got {sequences} x {frames}")
    if seed < 0:
        raise MsdnetError(None, f"seed must be >= 0, got {seed}")
    check_capacity(sequences, frames)
    root = Path(out)
    prepare_output(root, overwrite)
    writer = VodWriter(root, sim_rig.mounting)
    stride = id_stride(frames)
    all_ids: list[list[str]] = []
    entries = []
    bar = tqdm(total=sequences * frames, unit="frame", desc="simulate", disable=not progress)
    for k in range(sequences):
        sim = SequenceSim(seed, k, frames, sim_rig=sim_rig)
        ids = [frame_id(k, f, stride) for f in range(frames)]
        for fr in sim.frames():
            writer.write_frame(ids[fr.index], fr.lidar, fr.radar, fr.poses)
            bar.update(1)
        closures = loop_closures(sim.traj.xy)
        info = sim.info
        entries.append(
            {
                "index": k,
                "frame_ids": ids,
                "has_loop": bool(closures),
                "loop_planned": info.loop,
                "loop_closures": [[ids[i], ids[j]] for i, j in closures],
                "has_moving_objects": info.n_moving > 0,
                "n_moving_objects": info.n_moving,
                "cruise_speed": round(info.cruise_speed, 3),
                "path_length_m": round(float(sim.traj.speed.sum() * FRAME_DT), 2),
            }
        )
        all_ids.append(ids)
    bar.close()
    train, val = _splits(sequences, all_ids)
    writer.write_splits(train, val)
    doc = {
        "format_version": FORMAT_VERSION,
        "seed": seed,
        "frames_per_sequence": frames,
        "frame_rate_hz": round(1.0 / FRAME_DT),
        "id_stride": stride,
        "loop_closure_rule": "nearest earlier frame >= 150 frames back within 5 m",
        "sequences": entries,
    }
    if rig != "vod":
        doc["rig"] = rig
    writer.write_sequences(doc)
    return doc


@click.command("simulate")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path), help="Output folder.")
@click.option("--sequences", default=2, show_default=True, type=int, help="Number of sequences.")
@click.option("--frames", default=50, show_default=True, type=int, help="Frames per sequence (10 Hz).")
@click.option("--seed", default=0, show_default=True, type=int, help="Seed: same seed, same bytes.")
@click.option("--overwrite", is_flag=True, help="Replace a previous simulation in --out.")
@click.option(
    "--rig",
    type=click.Choice(sorted(SIM_RIGS)),
    default="vod",
    show_default=True,
    help="Vehicle: vod (HDL-64 + VoD-like radar) or astyx (VLP-16 + Astyx 6455-like radar; "
    "read it with --dataset sim-astyx).",
)
@one_line_errors
@checks_outputs(out="into")  # before any work
def simulate(out: Path, sequences: int, frames: int, seed: int, overwrite: bool, rig: str) -> None:
    """Simulate paired LiDAR / 4D-radar street sequences in the View-of-Delft layout."""
    start = time.perf_counter()
    doc = simulate_dataset(out, sequences, frames, seed, overwrite, rig=rig)
    elapsed = time.perf_counter() - start
    loops = sum(s["has_loop"] for s in doc["sequences"])
    drives = f"{sequences} drive{'s' if sequences > 1 else ''} of {frames} frame{'s' if frames > 1 else ''}"
    if sequences == 1:
        back = "it comes back to a place it passed" if loops else "it never comes back to a place it passed"
    elif loops == 0:
        back = "none of them comes back to a place it passed"
    else:
        back = f"{loops} of them come{'s' if loops == 1 else ''} back to a place they passed"
    click.echo(f"simulated {drives} into {out} in {elapsed:.1f} s; {back}")
