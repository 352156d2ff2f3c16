"""``msdnet-infer --rerun FILE.rrd``: a Rerun recording of the run, one frame per input.

Entities, all in the radar frame (x forward, y left, z up; metres), on the ``frame`` timeline
(sequence: the input's index in the run) and, for bag messages, the ``stamp`` timeline (header
stamp):

- ``radar``: the input radar points (N, 3), red;
- ``dense``: the output points (M, 3) coloured by confidence (viridis, 0 -> 1), with the
  confidence itself as the ``confidence`` component (M,) float32;
- ``lidar``: in ``--dataset`` mode, the frame's LiDAR (K, 3) in the radar frame, grey;
- ``source``: a text log line naming the input file, frame or message.

File and dataset modes log after the run from the written outputs (so ``--workers`` and
``--ray`` runs are recorded the same way); the bag mode logs each message as it goes. The file
is written under a temporary name (``io.atomic.temp_name``: pid-tagged, so the next run removes a killed
run's) and renamed when complete; a failure drops it. ``check_path`` refuses a path that cannot
be written (not ``.rrd``, a folder, a read-only place) before any work. Needs ``rerun-sdk``
(``[rerun]``).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.atomic import check_writable, temp_name, write_error
from msdnet.runtime.io.files import DENSE_COLUMNS, read_cloud

RADAR_RGB = (214, 39, 40)
LIDAR_RGB = (150, 150, 150)
TIMELINE = "frame"


def confidence_colors(confidence: np.ndarray) -> np.ndarray:
    """(M,) confidence in [0, 1] -> (M, 3) uint8 RGB from the viridis colormap."""
    from matplotlib import colormaps

    rgba = colormaps["viridis"](np.clip(np.asarray(confidence, np.float64), 0.0, 1.0))
    return np.round(rgba[:, :3] * 255.0).astype(np.uint8)


def check_path(path: str | Path) -> Path:
    """``--rerun`` before any work: a ``.rrd`` path that is not a folder, in a folder where a
    file can be created (one probe file, removed); a killed run's temporary recordings there
    are removed. -> the path; MsdnetError naming it otherwise."""
    target = Path(path)
    if target.suffix != ".rrd":
        raise MsdnetError(target, "--rerun writes a .rrd file; name it FILE.rrd")
    if target.is_dir():
        raise MsdnetError(target, "--rerun is a folder; name a FILE.rrd")
    check_writable(target, "file")  # the check every command shares
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise write_error(target, err) from None
    return target


class RerunLog:
    """An open recording; ``frame(...)`` per input, ``close()`` renames it into place."""

    def __init__(self, path: str | Path, app: str = "msdnet-infer") -> None:
        try:
            import rerun as rr
        except ImportError:
            raise MsdnetError("--rerun", "needs rerun-sdk: pip install 'msdnet[rerun]'") from None
        self.rr = rr
        self.path = check_path(path)
        self.tmp = self.path.parent / temp_name(self.path.name)
        self.rec = rr.RecordingStream(app)
        try:
            self.rec.save(str(self.tmp))
        except Exception as err:
            self.abort()
            cause = " ".join(str(err).split())[:200]
            raise MsdnetError(self.path, f"cannot write the recording: {cause}") from None
        self.rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def frame(
        self,
        index: int,
        label: str,
        radar: np.ndarray,
        dense: np.ndarray,
        confidence: np.ndarray,
        lidar: np.ndarray | None = None,
        stamp_ns: int | None = None,
    ) -> None:
        """Log one frame: radar (N, 3), dense (M, 3) with confidence (M,), LiDAR (K, 3) or None."""
        rr, rec = self.rr, self.rec
        rec.set_time(TIMELINE, sequence=index)
        if stamp_ns is not None:
            rec.set_time("stamp", timestamp=np.datetime64(int(stamp_ns), "ns"))
        rec.log("source", rr.TextLog(label))
        rec.log("radar", rr.Points3D(np.asarray(radar, np.float32)[:, :3], colors=RADAR_RGB, radii=0.12))
        conf = np.asarray(confidence, np.float32)
        rec.log(
            "dense",
            rr.Points3D(np.asarray(dense, np.float32)[:, :3], colors=confidence_colors(conf), radii=0.05),
            rr.AnyValues(confidence=conf),
        )
        if lidar is not None:
            rec.log("lidar", rr.Points3D(np.asarray(lidar, np.float32)[:, :3], colors=LIDAR_RGB, radii=0.02))

    def close(self) -> Path:
        """Flush, close and rename the recording into place; -> its path. A failure (the path
        became a folder, the disk is full) drops the temporary file and is one MsdnetError."""
        try:
            self.rec.flush()
            self.rec.disconnect()
            os.replace(self.tmp, self.path)
        except OSError as err:
            self.abort()
            raise write_error(self.path, err) from None
        return self.path

    def abort(self) -> None:
        """Drop the unfinished recording."""
        with contextlib.suppress(Exception):
            self.rec.disconnect()
        with contextlib.suppress(OSError):
            os.unlink(self.tmp)


@contextlib.contextmanager
def recording(path: str | Path | None) -> Iterator[RerunLog | None]:
    """``RerunLog(path)`` closed on success, dropped on error; ``None`` when ``path`` is None."""
    if path is None:
        yield None
        return
    log = RerunLog(path)
    try:
        yield log
    except BaseException:
        log.abort()
        raise
    log.close()


def log_files(path: str | Path, jobs: Sequence[tuple[str, str]], rows: Sequence[dict[str, Any]]) -> int:
    """File mode: log each (input, output) pair whose row has no error; -> frames logged."""
    ok = [(job, row) for job, row in zip(jobs, rows, strict=True) if "error" not in row]
    with recording(path) as log:
        assert log is not None
        for i, ((src, dst), _) in enumerate(tqdm(ok, unit="file", desc="rerun", disable=None)):
            dense = read_cloud(dst, columns=DENSE_COLUMNS)
            log.frame(i, src, read_cloud(src).xyz, dense.xyz, dense.column("confidence"))
    return len(ok)


def log_dataset(
    path: str | Path,
    dataset: str,
    root: Path,
    out: Path,
    split: str | None,
    max_frames: int | None,
    fmt: str,
    grid: Any,
) -> int:
    """Dataset mode: per frame the radar, the written dense cloud and the LiDAR (radar frame),
    prepared as ``infer_dataset.run_dataset`` prepares them (frames without an output are
    skipped); -> frames in the dataset selection."""
    from msdnet.runtime.io.datasets import open_dataset
    from msdnet.runtime.io.datasets.preprocess import preprocess_frame

    ds = open_dataset(dataset, root, split=split)
    ids = ds.frame_ids[:max_frames] if max_frames else ds.frame_ids
    with recording(path) as log:
        assert log is not None
        for i, fid in enumerate(tqdm(ids, unit="frame", desc="rerun", disable=None)):
            dst = out / f"{fid}.{fmt}"
            if not dst.is_file():  # a frame the run reported as failed
                continue
            frame = preprocess_frame(ds.load(fid), grid)
            dense = read_cloud(dst, columns=DENSE_COLUMNS)
            label = f"{dataset} {fid}"
            log.frame(i, label, frame.radar.xyz, dense.xyz, dense.column("confidence"), frame.lidar.xyz)
    return len(ids)
