"""``msdnet-infer INPUTS --out OUT``: the file mode, in this process, in ``--workers`` processes or on
Ray actors (``frontends/infer/ray_batch``); every way runs ``worker._run_one`` per file.

- ``collect_inputs``: files as given, folders expanded to the scans directly inside them;
- ``output_paths``: ``OUT/<stem>.<format>`` per input, refusing name clashes and inputs overwritten;
- ``pending_jobs``: the (input, output) pairs left to do (``--skip-existing`` resumes a batch);
- ``run_files``: the jobs run one way or another -> one summary row per file, in input order;
- ``summary``: the closing lines and the exit code (``EXIT_SOME_FAILED`` when a file failed),
  with every input row the engine did not use counted by reason, per file and in total
  (``drop_text``).
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from tqdm import tqdm

from msdnet.runtime.engine.pointcloud import DROP_REASONS
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.frontends.densify import DensifyOptions
from msdnet.runtime.frontends.infer.scans import is_scan, refuse_dataset_folder
from msdnet.runtime.frontends.infer.worker import WORKER, _init_worker, _run_one
from msdnet.runtime.io.files import READ_FORMATS

EXIT_SOME_FAILED = 1


def collect_inputs(inputs: tuple[Path, ...]) -> list[Path]:
    """Files as given, folders expanded to the scans directly inside them (sorted; ``scans.is_scan``
    leaves a licence or a frame list out); a folder holding a whole dataset is refused, naming the
    ``--dataset`` that reads it."""
    files: list[Path] = []
    for item in inputs:
        if item.is_dir():
            refuse_dataset_folder(item)
            found = sorted(
                p for p in item.iterdir() if p.is_file() and p.suffix.lower() in READ_FORMATS and is_scan(p)
            )
            if not found:
                raise MsdnetError(item, f"folder holds no point-cloud file ({' '.join(READ_FORMATS)})")
            files += found
        elif item.exists():
            files.append(item)
        else:
            raise MsdnetError(item, "no such file or folder")
    return files


def output_paths(files: list[Path], out: Path, fmt: str) -> list[Path]:
    """``OUT/<stem>.<fmt>`` per input; MsdnetError on a name clash or an output equal to an input."""
    targets = [out / f"{f.stem}.{fmt}" for f in files]
    seen: dict[Path, Path] = {}
    resolved_inputs = {f.resolve() for f in files}
    for src, dst in zip(files, targets, strict=True):
        if dst.resolve() in resolved_inputs:
            raise MsdnetError(dst, "output path equals an input path; choose another --out")
        if dst in seen:
            raise MsdnetError(dst, f"inputs {seen[dst]} and {src} would write the same output")
        seen[dst] = src
    return targets


def pending_jobs(
    files: list[Path], targets: list[Path], skip_existing: bool, png: bool
) -> tuple[list[tuple[str, str]], int]:
    """-> ((src, dst) pairs to run, how many were skipped because their output exists)."""
    jobs = [(str(s), str(d)) for s, d in zip(files, targets, strict=True)]
    if not skip_existing:
        return jobs, 0
    done = [Path(d).is_file() and (not png or Path(d).with_suffix(".png").is_file()) for _, d in jobs]
    return [j for j, d in zip(jobs, done, strict=True) if not d], sum(done)


def run_files(
    artifact: Any,
    model_dir: Path,
    provider: str,
    threads: int | None,
    jobs: list[tuple[str, str]],
    options: DensifyOptions,
    workers: int,
    trusted_key: Path | None,
    auto_pipe: Any = None,
    ray_address: str | None = None,
    ray_timeout: float = 30.0,
) -> list[dict[str, Any]]:
    """Run every (src, dst) job: on Ray actors (``ray_address``), here (one worker: ``auto_pipe``
    or a new Pipeline) or in ``workers`` spawned processes; -> one row per job, in job order."""
    bar = tqdm(total=len(jobs), unit="file", desc="msdnet-infer", disable=None)
    rows: list[dict[str, Any]] = []
    if ray_address is not None:
        from msdnet.runtime.frontends.infer.ray_batch import run_ray

        rows = run_ray(ray_address, artifact, provider, threads, jobs, options, bar, ray_timeout)
    elif workers == 1:
        from msdnet.runtime.engine.pipeline import Pipeline

        pipe = auto_pipe or Pipeline(artifact, provider=provider, threads=threads)
        WORKER.update(pipe=pipe, options=options)
        for job in jobs:
            rows.append(_run_one(*job))
            bar.update()
    else:
        ctx = multiprocessing.get_context("spawn")  # no onnxruntime/numba threads across fork
        key = None if trusted_key is None else str(trusted_key)
        initargs = (str(model_dir), provider, threads, options, os.getpid(), key)
        with ProcessPoolExecutor(workers, ctx, _init_worker, initargs) as pool:
            futures = {pool.submit(_run_one, *job): job for job in jobs}
            for fut in as_completed(futures):
                try:
                    rows.append(fut.result())
                except Exception as err:  # a worker died (killed, out of memory) or failed to start
                    cause = " ".join(str(err).split())[:200] or type(err).__name__
                    rows.append({"file": futures[fut][0], "error": f"{futures[fut][0]}: worker: {cause}"})
                bar.update()
        order = {src: i for i, (src, _) in enumerate(jobs)}
        rows.sort(key=lambda r: order[r["file"]])
    bar.close()
    return rows


def summary(rows: list[dict[str, Any]], wall: float, skipped: int = 0) -> tuple[str, int]:
    """The summary lines of a run (files, points, drops, notes, failures) and its exit code."""
    failed = [r for r in rows if "error" in r]
    ok = len(rows) - len(failed)
    p_in = sum(r["points_in"] for r in rows if "error" not in r)
    p_out = sum(r["points_out"] for r in rows if "error" not in r)
    totals = {k: sum(r.get(k, 0) for r in rows if "error" not in r) for k in DROP_REASONS}
    dropped = [r for r in rows if "error" not in r and any(r.get(k) for k in DROP_REASONS)]
    per = f", {wall / max(ok, 1):.3f} s/file" if ok else ""
    skip = f", {skipped} skipped (output exists)" if skipped else ""
    drop = f" (dropped {drop_text(totals)})" if any(totals.values()) else ""
    lines = [
        f"files: {ok} ok, {len(failed)} failed{skip}; points in {p_in}{drop}, out {p_out}; "
        f"time {wall:.2f} s{per}"
    ]
    lines += [f"  dropped: {r['file']}: {drop_text(r, per_file=True)}" for r in dropped]
    lines += [
        f"  {'note' if r['points_out'] else 'empty'}: {r['file']}: {'; '.join(r['notes'])}"
        for r in rows
        if r.get("notes")
    ]
    lines += [f"  FAILED {r['error']}" for r in failed]
    return "\n".join(lines), (EXIT_SOME_FAILED if failed else 0)


def drop_text(counts: dict[str, Any], per_file: bool = False) -> str:
    """``counts`` (``DROP_REASONS`` keys) -> ``"8 with NaN/Inf, 40 outside the grid"``, the
    reasons with a count only; ``per_file``: ``"3 rows with NaN/Inf (or beyond float32), ..."``."""
    parts = [f"{counts[k]} {words}" for k, words in DROP_REASONS.items() if counts.get(k)]
    if per_file and counts.get("dropped_nonfinite"):
        parts[0] = f"{counts['dropped_nonfinite']} rows with NaN/Inf (or beyond float32)"
    return ", ".join(parts)
