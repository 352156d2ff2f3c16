"""``msdnet-infer``: run an exported model over radar files, write dense clouds (no torch).

Inputs are files or folders (the scans directly inside a folder, sorted) of any format
``runtime/io/files`` reads. Before any scan runs (``frontends/infer/scans``), a folder that holds a
whole dataset is refused, naming the ``--dataset`` that reads it, and scans whose columns the model
does not read stop the run in one line that names the shipped models that read them. Each output
is ``OUT/<input stem>.<format>`` with columns ``x y z confidence`` (radar frame, metres;
confidence = occupancy). A ``.bin`` is read with
``--layout`` / ``--columns``, else with the model's training layout (``runtime/io/layouts``). One bad
file does not stop the others: the summary names it and the exit code is 1. Bad arguments exit 2
with one line; an option that does not apply to the inputs is refused, or noted where it applies to
some of them (``frontends/infer/option_use``).
The output is the model's decoded points plus, where the manifest has a keep rule
(``keep_radar_threshold``), the input radar points its head finds support for.
``--keep-radar`` (off by default) appends every other input radar point inside the grid box too,
confidence 1 (``Pipeline.__call__(keep_radar=True)``).

Faults: ``--out`` must be a writable folder that holds no input (checked once, up front); a
killed run leaves no worker process (each worker exits when its parent is gone) and the next
run removes its temporary files; ``--skip-existing`` resumes a batch. Rows the engine does not
use (NaN/Inf or values beyond float32, outside the grid, over the voxel cap) are dropped and
counted by reason per file and in the summary. Same seed, same
bytes: with ``--provider cpu``, the same model, onnxruntime build and CPU, outputs do not depend
on ``--workers`` or ``--threads`` (``--threads`` is kept as given in every worker; unset, each of
N workers gets cores // N); tests/test_faults.py checks --threads 1/2 and --workers 1/2.
``--trusted-key PUB`` refuses a model whose ``manifest.sig`` is missing or not by that key
(``runtime/model/signing``).

``--provider auto``, the default (``runtime/providers/provider_auto``), runs each graph on whichever
installed f32 engine, onnxruntime or OpenVINO, measured faster here: measured by the first run (a
few seconds, said in one line on stderr), then cached per model, CPU and library versions; ``-v``
prints the picks, times and cache notes. Without OpenVINO it is ``cpu``. Its outputs are within
the export tolerances of ``cpu``'s, except where the manifest has a gate and the dense head is
the faster head here (``runtime/providers/provider_head``): auto then runs the dense head, the
reference the gated head approximates, and decodes the few points the gate drops too.
``--provider auto-bf16`` lets OpenVINO compute in bfloat16 (CPUs with bf16 units): not within
those tolerances; on the Astyx selection slice it changed CD, MHD and F@0.5 by
under 0.6 % (docs/latency.md).

``--dataset vod|astyx|sim|sim-astyx`` reads one dataset folder instead (``frontends/infer/dataset``): each
frame's radar is densified and compared with its LiDAR, and the summary says how much denser and
how much closer to the LiDAR the output is than the radar.

Robotics (optional extras): ``BAG --topic T`` densifies a ROS 1/2 bag's PointCloud2 topic into a
ROS 2 bag (``runtime/io/rosbag``), ``--ray [ADDRESS]`` runs the files on Ray actors
(``runtime/frontends/infer/ray_batch``), ``--rerun FILE.rrd`` records the run for Rerun
(``runtime/io/rerun_log``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import click

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.frontends.densify import DensifyOptions
from msdnet.runtime.frontends.infer.files import (
    EXIT_SOME_FAILED,
    collect_inputs,
    output_paths,
    pending_jobs,
    run_files,
    summary,
)
from msdnet.runtime.frontends.infer.guards import (
    check_extras,
    check_out,
    clamp_workers,
    prepare_out,
    usable_cores,
)
from msdnet.runtime.frontends.infer.option_use import check_option_use
from msdnet.runtime.frontends.infer.scans import check_scan_columns
from msdnet.runtime.frontends.model_args import BUNDLED_MODEL, check_model_options, resolve_model
from msdnet.runtime.io.files import DENSE_COLUMNS, WRITE_FORMATS
from msdnet.runtime.io.layouts import LAYOUTS, resolve_bin_columns

OUT_COLUMNS = DENSE_COLUMNS  # columns of every written cloud


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("inputs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--model",
    type=click.Path(path_type=Path),
    help="A shipped model's name (astyx-lite, sim-lite, ...) or an msdnet-export folder [sim-lite].",
)
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Output folder.")
@click.option("--format", "fmt", type=click.Choice(WRITE_FORMATS), default="npy", show_default=True)
@click.option("--steps", type=click.IntRange(min=1), help="DDIM steps [manifest T_m].")
@click.option(
    "--threshold", type=float, help="One occupancy threshold everywhere [manifest: its one, or by range]."
)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Noise seed.")
@click.option("--png", is_flag=True, help="Also write a BEV picture per file.")
@click.option(
    "--keep-radar",
    is_flag=True,
    help="Also output every input radar point in the grid (confidence 1), not only those the "
    "model's keep rule keeps. Off: the model's output.",
)
@click.option(
    "--workers", type=click.IntRange(min=1), default=1, show_default=True, help="Processes (<= CPU cores)."
)
@click.option("--skip-existing", is_flag=True, help="Skip inputs whose output exists (resume a batch).")
@click.option(
    "--trusted-key",
    type=click.Path(path_type=Path),
    help="Ed25519 public key (PEM): refuse a model not signed with it (msdnet-export --sign).",
)
@click.option(
    "--provider",
    default="auto",
    show_default=True,
    help="auto (per graph the faster installed f32 engine, onnxruntime or OpenVINO, and the faster "
    "head; measured on the first run, then cached), cpu (onnxruntime: byte-reproducible), cpu-shared "
    "(onnxruntime with one thread pool for every graph), auto-bf16 (auto with OpenVINO in bfloat16: "
    "fastest on CPUs with bf16 units), openvino, openvino-bf16, cuda or tensorrt.",
)
@click.option(
    "-v",
    "--verbose",
    is_flag=True,
    help="With --provider auto[-bf16]: print each graph's engine, the head pick and cache notes.",
)
@click.option("--threads", type=click.IntRange(min=1), help="Intra-op threads per worker.")
@click.option(
    "--dataset",
    type=click.Choice(["vod", "astyx", "sim", "sim-astyx"]),
    help="INPUTS is one dataset folder (or the simulator's output): densify its radar and compare "
    "with its LiDAR.",
)
@click.option("--split", type=click.Choice(["train", "val"]), help="With --dataset: one split [all].")
@click.option("--frames", "max_frames", type=click.IntRange(min=1), help="With --dataset: first N frames.")
@click.option("--topic", help="INPUTS is one ROS 1/2 bag: densify this PointCloud2 topic into a ROS 2 bag.")
@click.option("--field", "fields", multiple=True, metavar="COLUMN=FIELD", help="With --topic: map a field.")
@click.option(
    "--bag-storage", type=click.Choice(["sqlite3", "mcap"]), help="With --topic [input's; ROS 1: mcap]."
)
@click.option(
    "--ray",
    "ray_address",
    is_flag=False,
    flag_value="local",
    metavar="[ADDRESS]",
    help="Run the files on Ray actors: local, auto or ray://HOST:PORT (the optional [ray] extra).",
)
@click.option(
    "--ray-timeout",
    type=click.FloatRange(min=0.0, min_open=True),
    default=30.0,
    show_default=True,
    help="With --ray ADDRESS: seconds it may take to answer.",
)
@click.option("--rerun", type=click.Path(path_type=Path), help="Also write a Rerun recording FILE.rrd.")
@click.option(
    "--layout", type=click.Choice(list(LAYOUTS)), help="Columns of .bin inputs by layout [the model's data]."
)
@click.option("--columns", "bin_columns", metavar="X,Y,Z", help=".bin columns by name (not with --layout).")
@one_line_errors
def main(
    inputs: tuple[Path, ...],
    model: Path | None,
    out: Path,
    fmt: str,
    steps: int | None,
    threshold: float | None,
    seed: int,
    png: bool,
    keep_radar: bool,
    workers: int,
    skip_existing: bool,
    trusted_key: Path | None,
    provider: str,
    threads: int | None,
    dataset: str | None,
    split: str | None,
    max_frames: int | None,
    topic: str | None,
    fields: tuple[str, ...],
    bag_storage: str | None,
    ray_address: str | None,
    ray_timeout: float,
    rerun: Path | None,
    layout: str | None,
    bin_columns: str | None,
    verbose: bool = False,
) -> None:
    """Densify radar point clouds with an exported MSDNet (or R2LDM) model."""

    model_dir = resolve_model(model)
    artifact = check_model_options(model_dir, trusted_key, provider, threshold, steps)
    columns, _ = resolve_bin_columns(layout, bin_columns, artifact.manifest)  # file mode .bin
    mode = "topic" if topic is not None else "dataset" if dataset is not None else "files"
    check_extras(png, dataset is not None, fmt)
    check_option_use(click.get_current_context(), inputs, mode, provider, lambda s: click.echo(s, err=True))
    options = DensifyOptions(  # the one set of options every mode (and every worker) runs with
        steps=steps,
        threshold=threshold,
        seed=seed,
        keep_radar=keep_radar,
        fmt=fmt,
        png=png,
        bin_columns=columns,
    )
    if rerun is not None:
        from msdnet.runtime.io.rerun_log import check_path

        check_path(rerun)  # writable .rrd, checked before any work like --out
    if topic is not None:
        if dataset or ray_address or png or skip_existing or workers > 1:
            raise MsdnetError(
                "--topic", "one bag, one process: not with --dataset/--ray/--png/--skip-existing/--workers"
            )
        from msdnet.runtime.frontends.infer.bag import bag_mode

        _announce_auto(artifact, provider, threads, verbose)
        start = time.perf_counter()
        rows = bag_mode(artifact, provider, threads, inputs, out, topic, fields, bag_storage, rerun, options)
        text, code = summary(rows, time.perf_counter() - start)
        click.echo(text.replace("files:", "messages:", 1).replace(" s/file", " s/message"))
        raise SystemExit(code)
    if fields or bag_storage:
        raise MsdnetError("--field/--bag-storage", "only apply with --topic")
    if ray_address is not None and (
        dataset or ray_address not in ("local", "auto") and Path(ray_address).exists()
    ):
        raise MsdnetError("--ray", f"takes a cluster address, not {ray_address!r}; put --ray after INPUTS")
    if ray_address is not None and workers > 1:
        raise MsdnetError("--workers", "not with --ray (Ray runs one actor per --threads CPUs)")
    check_out(out, inputs)
    if dataset is not None:
        if skip_existing:
            raise MsdnetError("--skip-existing", "only applies to file mode, not --dataset")
        if len(inputs) != 1 or not inputs[0].is_dir():
            raise MsdnetError(" ".join(map(str, inputs)), "--dataset takes exactly one dataset folder")
        from msdnet.runtime.frontends.infer.dataset import check_radar_columns
        from msdnet.runtime.io.atomic import check_writable

        check_writable(out, "into")  # the output first, before the dataset is read
        check_radar_columns(artifact, dataset, inputs[0], split)
        _announce_auto(artifact, provider, threads, verbose)
        _dataset_mode(artifact, provider, threads, dataset, inputs, out, split, max_frames, options)
        if rerun is not None:
            from msdnet.runtime.io.rerun_log import log_dataset

            log_dataset(rerun, dataset, inputs[0], out, split, max_frames, fmt, artifact.grid)
        return
    if split is not None or max_frames is not None:
        raise MsdnetError("--split/--frames", "only apply with --dataset")
    files = collect_inputs(inputs)
    check_extras(False, False, fmt, files)
    check_scan_columns(files, columns, model_dir, artifact.inputs.columns, BUNDLED_MODEL.parent)
    targets = output_paths(files, out, fmt)
    prepare_out(out)  # writable, and a killed run's temporary files removed
    start = time.perf_counter()
    jobs, skipped = pending_jobs(files, targets, skip_existing, png)
    workers = clamp_workers(workers, len(jobs))
    if threads is None and workers > 1:
        threads = max(1, usable_cores() // workers)  # outputs do not depend on it
    if threads is None and ray_address is not None:
        from msdnet.runtime.frontends.infer.ray_batch import DEFAULT_THREADS

        threads = DEFAULT_THREADS  # the actors' threads: their engine picks are the ones made here
    auto_pipe = _announce_auto(artifact, provider, threads, verbose)  # workers then read its cache
    rows = run_files(
        artifact,
        model_dir,
        provider,
        threads,
        jobs,
        options,
        workers,
        trusted_key,
        auto_pipe=auto_pipe,
        ray_address=ray_address,
        ray_timeout=ray_timeout,
    )
    if rerun is not None:
        from msdnet.runtime.io.rerun_log import log_files

        log_files(rerun, jobs, rows)
    text, code = summary(rows, time.perf_counter() - start, skipped)
    click.echo(text)
    if code:
        raise SystemExit(code)


def _announce_auto(artifact: Any, provider: str, threads: int | None, verbose: bool) -> Any:
    """``--provider auto``: pick each graph's engine once, here (measured, or read from the cache the
    workers then read too); ``-v`` prints the picks. -> that Pipeline, None for other providers."""
    if provider.strip().lower() not in ("auto", "auto-bf16"):
        return None
    from msdnet.runtime.engine.pipeline import Pipeline

    pipe = Pipeline(artifact, provider=provider, threads=threads, notify=lambda s: click.echo(s, err=True))
    if verbose:
        click.echo("\n".join(pipe.auto.lines()), err=True)
    return pipe


def _dataset_mode(
    artifact: Any,
    provider: str,
    threads: int | None,
    dataset: str,
    inputs: tuple[Path, ...],
    out: Path,
    split: str | None,
    max_frames: int | None,
    options: DensifyOptions,
) -> None:
    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.frontends.infer.dataset import run_dataset, summary_lines

    prepare_out(out)  # writable, and a killed run's temporary files removed
    pipe = Pipeline(artifact, provider=provider, threads=threads)
    rows, failed = run_dataset(pipe, dataset, inputs[0], out, split, max_frames, options)
    name = "R2LDM" if artifact.kind == "r2ldm" else "MSDNet"
    if options.keep_radar:
        name += "+radar"  # the scored output is the union (--keep-radar), not the model alone
    click.echo("\n".join(summary_lines(rows, name)))
    click.echo(f"wrote {len(rows)} clouds{' and pictures' if options.png else ''} to {out}")
    if failed:
        click.echo("\n".join([f"{len(failed)} frames failed:", *(f"  FAILED {f}" for f in failed)]))
        raise SystemExit(EXIT_SOME_FAILED)
