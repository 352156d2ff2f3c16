"""``msdnet-bench fuzz``: seeded byte mutations and truncations of valid inputs, through every reader.

Readers: ``ply`` (binary and text), ``pcd`` (binary and ASCII), ``npy``, ``bin`` (VoD radar),
``txt`` (Astyx radar, header line) and ``msg`` (a CDR-serialized sensor_msgs/PointCloud2 through
``io.rosbag.message_cloud``, the bag mode's decoder; needs the ``[ros]`` extra). Each case takes
one valid input, applies 1-3 mutations drawn from a seeded generator (flip bytes, overwrite a
run with random or digit bytes, insert, delete or repeat a run, truncate), and reads it. The
rule: the reader returns a cloud (then written back with ``write_cloud`` and read again) or
raises ``MsdnetError`` whose message is one line; any other exception, a multi-line message,
a case over ``CASE_LIMIT_S`` seconds (a hang, stopped by SIGALRM) or a temporary file left in the
folder is a failure, reported with the reader, case number and seed so it can be replayed.
"""

from __future__ import annotations

import contextlib
import functools
import json
import signal
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import click
import numpy as np

from msdnet.runtime.engine.pointcloud import PointCloud
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import checks_outputs
from msdnet.runtime.io.files import VOD_RADAR_COLUMNS, WRITE_FORMATS, read_cloud, write_cloud

READERS = ("ply", "pcd", "npy", "bin", "txt", "msg")
CASE_LIMIT_S = 10  # one read longer than this counts as a hang
MODEL_COLUMNS = ("x", "y", "z", "rcs", "v_r_compensated")  # what a bag read picks from a message


@dataclass
class Tally:
    """Per reader: cases read, refused (one line) and the failures (anything else)."""

    read: int = 0
    refused: int = 0
    failures: list[str] = field(default_factory=list)
    seconds: float = 0.0


def valid_inputs(folder: Path, seed: int = 0, n: int = 24) -> dict[str, list[tuple[str, bytes]]]:
    """Per reader, (file name, bytes) of valid inputs of ``n`` VoD radar rows, written by the
    project's writers (and an Astyx-style text file)."""
    rng = np.random.default_rng(seed)
    pts = (rng.normal(0, 5, (n, 7)) + [20, 0, 0.5, 0, 0, 0, 0]).astype(np.float32)
    cloud = PointCloud(pts, VOD_RADAR_COLUMNS)
    out: dict[str, list[tuple[str, bytes]]] = {r: [] for r in READERS}
    folder.mkdir(parents=True, exist_ok=True)
    for fmt in ("ply", "pcd", "npy", "bin"):
        path = write_cloud(folder / f"seed.{fmt}", cloud)
        out[fmt].append((path.name, path.read_bytes()))
    import plyfile

    rows = np.empty(n, dtype=[(c, "<f4") for c in VOD_RADAR_COLUMNS])
    for i, c in enumerate(VOD_RADAR_COLUMNS):
        rows[c] = pts[:, i]
    text = folder / "seed_text.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(rows, "vertex")], text=True).write(str(text))
    out["ply"].append((text.name, text.read_bytes()))
    pcd_ascii = "\n".join(
        ["VERSION 0.7", "FIELDS x y z rcs", "SIZE 4 4 4 4", "TYPE F F F F", "COUNT 1 1 1 1"]
        + [f"WIDTH {n}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", "DATA ascii"]
        + [" ".join(f"{v:.4f}" for v in row[:4]) for row in pts]
    )
    out["pcd"].append(("seed_ascii.pcd", (pcd_ascii + "\n").encode()))
    astyx = "\nX Y Z V_r Mag\n" + "\n".join(" ".join(f"{v:.5f}" for v in row[:5]) for row in pts) + "\n"
    out["txt"].append(("seed.txt", astyx.encode()))
    out["msg"] = [(f"message {i}", raw) for i, raw in enumerate(_messages(pts))]
    return out


def _messages(pts: np.ndarray) -> list[bytes]:
    """CDR bytes of two valid PointCloud2 messages (height 1, and height 2 with row padding)."""
    from msdnet.runtime.io.rosbag import POINTCLOUD2, make_pointcloud2

    store = _store()
    flat = make_pointcloud2(store, pts, VOD_RADAR_COLUMNS, (1_700_000_000, 5), "radar")
    tall = make_pointcloud2(store, pts, VOD_RADAR_COLUMNS, (1_700_000_000, 6), "radar")
    step = tall.point_step
    half = len(pts) // 2
    padded = np.zeros((2, half * step + 8), np.uint8)  # two rows of `half` points, 8 padding bytes
    padded[:, : half * step] = np.asarray(tall.data[: 2 * half * step]).reshape(2, half * step)
    tall.height, tall.width, tall.row_step, tall.data = 2, half, half * step + 8, padded.reshape(-1)
    return [bytes(store.serialize_cdr(m, POINTCLOUD2)) for m in (flat, tall)]


@functools.cache
def _store() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """1-3 seeded mutations of ``data``: byte flips, overwritten runs (random or digits), inserted,
    deleted or repeated runs, or a truncation."""
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        if not buf:
            break
        kind = int(rng.integers(0, 7))
        at = int(rng.integers(0, len(buf)))
        run = int(rng.integers(1, 9))
        if kind == 0:  # flip bits
            for i in rng.integers(0, len(buf), run):
                buf[int(i)] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:  # random run
            buf[at : at + run] = rng.integers(0, 256, run, dtype=np.uint8).tobytes()
        elif kind == 2:  # digits (numbers in a header: counts, sizes, shapes)
            buf[at : at + run] = bytes(rng.choice(list(b"0123456789"), run).tolist())
        elif kind == 3:  # insert
            buf[at:at] = rng.integers(0, 256, run, dtype=np.uint8).tobytes()
        elif kind == 4:  # delete
            del buf[at : at + run]
        elif kind == 5:  # repeat a run
            buf[at:at] = buf[at : at + run * 4]
        else:  # truncate
            del buf[at:]
    return bytes(buf)


@contextlib.contextmanager
def _time_limit(seconds: int) -> Iterator[None]:
    """SIGALRM after ``seconds`` raises TimeoutError here (main thread only; elsewhere no limit)."""

    def alarm(signum: int, frame: Any) -> None:
        raise TimeoutError(f"no answer within {seconds} s")

    try:
        old = signal.signal(signal.SIGALRM, alarm)
    except ValueError:  # not the main thread
        yield
        return
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _read_file(path: Path, data: bytes, out: Path) -> None:
    path.write_bytes(data)
    cloud = read_cloud(path, kind="vod_radar" if path.suffix == ".bin" else None)
    if len(cloud.columns) >= 3:  # written back and read again: the writer takes whatever was read
        fmt = path.suffix if path.suffix.lstrip(".") in WRITE_FORMATS else ".npy"  # .txt is read-only
        back = read_cloud(write_cloud(out / f"back{fmt}", cloud), columns=cloud.columns)
        if back.points.shape != cloud.points.shape:
            raise AssertionError(f"read back {back.points.shape}, wrote {cloud.points.shape}")


def _read_message(data: bytes) -> None:
    from msdnet.runtime.io.rosbag import message_cloud

    store = _store()
    message_cloud(store.deserialize_cdr, data, MODEL_COLUMNS, {}, "/radar/points message 0")


def run_fuzz(
    folder: Path,
    cases: int,
    seed: int = 0,
    readers: tuple[str, ...] = READERS,
    progress: Callable[[str, int], None] | None = None,
) -> dict[str, Tally]:
    """``cases`` mutated inputs per reader in ``folder`` (module docstring); -> tallies."""
    folder.mkdir(parents=True, exist_ok=True)
    seeds = valid_inputs(folder / "seeds", seed)
    tallies: dict[str, Tally] = {}
    for reader in readers:
        tally = tallies[reader] = Tally()
        work = folder / reader
        work.mkdir(exist_ok=True)
        start = time.perf_counter()
        for case in range(cases):
            rng = np.random.default_rng([seed, READERS.index(reader), case])  # replayable alone
            name, valid = seeds[reader][case % len(seeds[reader])]
            data = mutate(valid, rng)
            where = f"{reader} case {case} (seed {seed}, from {name})"
            try:
                with _time_limit(CASE_LIMIT_S):
                    if reader == "msg":
                        _read_message(data)
                    else:
                        _read_file(work / f"case{Path(name).suffix}", data, work)
                tally.read += 1
            except MsdnetError as err:
                if "\n" in str(err):
                    tally.failures.append(f"{where}: a refusal of more than one line: {str(err)!r}")
                else:
                    tally.refused += 1
            except Exception as err:  # the point of the fuzz: report, do not stop
                tally.failures.append(f"{where}: {type(err).__name__}: {' '.join(str(err).split())[:200]}")
            left = [p.name for p in work.iterdir() if p.name.endswith(".tmp")]
            if left:
                tally.failures.append(f"{where}: temporary files left: {' '.join(left)}")
            if progress is not None:
                progress(reader, case)
        tally.seconds = time.perf_counter() - start
    return tallies


def report(tallies: dict[str, Tally], cases: int, seed: int) -> str:
    lines = [f"fuzz: {cases} cases per reader, seed {seed}"]
    for reader, t in tallies.items():
        lines.append(
            f"  {reader:4s} read {t.read:5d}  refused {t.refused:5d}  failures {len(t.failures):3d}  "
            f"{t.seconds:6.1f} s"
        )
        lines += [f"    FAIL {f}" for f in t.failures[:20]]
    return "\n".join(lines)


@click.command("fuzz")
@click.option("--cases", type=click.IntRange(min=1), default=2000, show_default=True, help="Per reader.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--reader", "readers", multiple=True, type=click.Choice(READERS), help="Only these [all].")
@click.option("--work", type=click.Path(path_type=Path), help="Folder for the cases [a temporary one].")
@click.option("--json", "json_out", type=click.Path(path_type=Path), help="Also write the tallies as JSON.")
@one_line_errors
@checks_outputs(work="into", json_out="file")  # before any work
def fuzz_command(
    cases: int, seed: int, readers: tuple[str, ...], work: Path | None, json_out: Path | None
) -> None:
    """Mutated and truncated inputs through every reader: read, or refused in one line."""
    import tempfile

    chosen = readers or READERS
    if "msg" in chosen:
        try:
            import rosbags  # noqa: F401
        except ImportError:
            chosen = tuple(r for r in chosen if r != "msg")
            click.echo("note: no rosbags ([ros] extra): PointCloud2 messages skipped", err=True)
    with tempfile.TemporaryDirectory(prefix="msdnet-fuzz-") as tmp:
        tallies = run_fuzz(work or Path(tmp), cases, seed, chosen)
    click.echo(report(tallies, cases, seed))
    if json_out is not None:
        from msdnet.runtime.io.atomic import atomic_output

        body = {
            r: {"read": t.read, "refused": t.refused, "failures": t.failures, "seconds": t.seconds}
            for r, t in tallies.items()
        }
        with atomic_output(json_out) as tmp_path:
            Path(tmp_path).write_text(json.dumps({"cases": cases, "seed": seed, "readers": body}, indent=1))
    if any(t.failures for t in tallies.values()):
        sys.exit(1)
