"""``msdnet-export CHECKPOINT --out DIR [--verify]``: checkpoint -> ONNX graphs + manifest.json.

The folder is built under a temporary name next to ``--out`` and renamed into place only when
complete (and, with ``--verify``, only when verification passes), so ``--out`` is always either
the previous artifact or the new one. Exit 1 when verification fails, 2 on bad input.
Folders and files get the usual permissions (0777 / 0666 minus the umask). A killed export
leaves its temporary folder behind; the next export into the same parent folder removes it.
``--sign KEY`` (an ed25519 private key, PEM) writes ``manifest.sig`` (``runtime/model/signing``), which
``msdnet-infer --trusted-key`` checks. The checkpoint is checked first: its preset name must be
known and ``model.safetensors`` must load (a corrupt file is one line, whatever its hash says).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import numpy as np

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.frontends.infer.option_use import given
from msdnet.runtime.io.atomic import checks_outputs, clean_stale_temps, temp_name
from msdnet.runtime.io.datasets import DATASET_NAMES
from msdnet.runtime.model.artifact import MANIFEST
from msdnet.training.config import MODEL_PRESETS, ModelConfig

if TYPE_CHECKING:
    from msdnet.export.verify import VerifyReport

EXIT_VERIFY_FAILED = 1


def verification_frames(
    cfg: ModelConfig, data: Path | None, dataset: str | None, count: int
) -> tuple[list[np.ndarray], str]:
    """(frames (N, C) float32 in ``cfg.radar_columns`` order, description): ``count`` real radar
    scans spread over the dataset, or random points in the grid when no data is given."""
    if data is None:
        from msdnet.export.graphs import tracing_points

        frames = [tracing_points(cfg, n=300, seed=100 + i) for i in range(count)]
        return frames, f"{count} random frames (no --data)"
    from msdnet.runtime.io.datasets import open_dataset

    if dataset is None:
        raise MsdnetError("--dataset", "needed with --data (astyx, vod or sim)")
    ds = open_dataset(dataset, data)
    ids = list(ds.frame_ids)
    if not ids:
        raise MsdnetError(data, "dataset has no frames")
    picks = sorted({int(i) for i in np.linspace(0, len(ids) - 1, min(count, len(ids)))})
    frames = [ds[i].radar.select(cfg.radar_columns).points for i in picks]
    names = ", ".join(ids[i] for i in picks)
    return frames, f"{dataset} frames {names}"


def _fsync_folder(folder: Path) -> None:
    for path in folder.iterdir():
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def check_out(out: Path) -> None:
    """Refuse an ``--out`` that is a symlink, a file, or a non-empty folder that is no artifact."""
    if out.is_symlink():
        raise MsdnetError(out, "is a symlink; refusing to replace it")
    if out.exists() and not out.is_dir():
        raise MsdnetError(out, "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / MANIFEST).is_file():
        raise MsdnetError(out, "folder is not empty and holds no manifest.json; refusing to replace it")


def publish(tmp: Path, out: Path) -> None:
    """Move the finished folder ``tmp`` to ``out``, replacing a previous artifact there."""
    check_out(out)
    if not out.exists():
        os.replace(tmp, out)
        return
    old = out.with_name(f".{out.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    os.replace(out, old)
    os.replace(tmp, out)
    shutil.rmtree(old, ignore_errors=True)


def load_for_export(checkpoint: Path) -> tuple[Any, ModelConfig, Any]:
    """(model, config, state) of ``checkpoint``; every failure is one MsdnetError: an unknown
    preset name, weights that do not load (safetensors' own error on a corrupt file whose
    hash in checkpoint.json was updated or removed)."""
    from msdnet.training.recipe.checkpoint import MODEL_FILE, load_checkpoint, read_checkpoint

    folder, cfg, _ = read_checkpoint(checkpoint)
    if cfg.preset not in MODEL_PRESETS:
        raise MsdnetError(
            folder / "checkpoint.json",
            f"unknown preset {cfg.preset!r} in model_config (known: {', '.join(MODEL_PRESETS)})",
        )
    try:
        return load_checkpoint(checkpoint)
    except MsdnetError:
        raise
    except Exception as err:  # safetensors raises its own SafetensorError; torch its own
        cause = " ".join(str(err).split())[:200] or type(err).__name__
        raise MsdnetError(folder / MODEL_FILE, f"cannot load weights: {cause}") from None


class VerificationFailed(Exception):
    """``--verify`` measured errors beyond tolerance; ``report`` says which."""

    def __init__(self, report: VerifyReport) -> None:
        super().__init__("verification failed")
        self.report = report


def export_model(
    model: Any,
    kind: str,
    cfg: ModelConfig,
    out: Path,
    source: str,
    frames: list[np.ndarray] | None = None,
    frames_source: str = "",
    seed: int = 0,
    threads: int | None = None,
    sign_key: Path | None = None,
    encoder_form: str = "rulebook",
) -> tuple[dict[str, Any], VerifyReport | None]:
    """Export ``model`` (a student or R2LDM torch module) into the artifact folder ``out``.

    With ``frames`` ((N, C) float32 radar scans in ``cfg.radar_columns`` order) the artifact is
    verified before it is published; :class:`VerificationFailed` leaves ``out`` unchanged.
    ``sign_key``: an ed25519 private key (PEM) that signs the final manifest (``manifest.sig``).
    ``encoder_form``: "rulebook" or "pairs" (``export.encoder_pairs``: the same weights, only the
    real neighbour pairs multiplied).
    Returns (manifest, verification report or None).
    """
    import torch

    from msdnet.export.graphs import export_all
    from msdnet.export.manifest import build_manifest, write_manifest
    from msdnet.export.verify import verify_artifact

    check_out(out)
    key = None
    if sign_key is not None:
        from msdnet.runtime.model.signing import load_private_key

        key = load_private_key(sign_key)  # a bad key fails before any work
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        clean_stale_temps(out.parent)  # a killed export's leftovers
        tmp = out.parent / temp_name(out.name)
        tmp.mkdir()  # 0777 minus the umask, like any folder
    except OSError as err:
        raise MsdnetError(out, f"cannot create the artifact folder ({err.strerror or err})") from None
    report = None
    try:
        torch.manual_seed(seed)
        params, _ = export_all(model, kind, cfg, tmp, encoder_form)
        manifest = build_manifest(tmp, kind, cfg, params, source, encoder_form=encoder_form)
        write_manifest(tmp, manifest)
        if frames is not None:
            report = verify_artifact(model, kind, cfg, tmp, frames, frames_source, seed, threads)
            if not report.ok:
                raise VerificationFailed(report)
            manifest["verification"] = report.to_dict()
            write_manifest(tmp, manifest)
        if key is not None:
            from msdnet.runtime.model.signing import sign_folder

            sign_folder(tmp, key, MANIFEST)
        _fsync_folder(tmp)
        publish(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return manifest, report


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("checkpoint", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Artifact folder.")
@click.option("--verify", is_flag=True, help="Compare torch and onnxruntime; fail beyond tolerance.")
@click.option("--data", type=click.Path(path_type=Path), help="Dataset root for --verify frames.")
@click.option("--dataset", type=click.Choice(DATASET_NAMES), help="Layout of --data.")
@click.option("--frames", type=click.IntRange(min=1), default=3, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True, help="Noise seed for --verify.")
@click.option("--threads", type=click.IntRange(min=1), help="torch and onnxruntime threads.")
@click.option(
    "--sign",
    "sign_key",
    type=click.Path(path_type=Path),
    help="Ed25519 private key (PEM): sign the manifest (manifest.sig) for msdnet-infer --trusted-key.",
)
@click.option(
    "--threshold",
    type=click.FloatRange(0.0, 1.0, min_open=True, max_open=True),
    help="Default occupancy threshold written to the manifest [the checkpoint's config].",
)
@click.option(
    "--guidance",
    type=click.FloatRange(min=0.0),
    help="R2LDM: classifier-free guidance weight w baked into the step graph [the config's, 1 = off].",
)
@click.option(
    "--steps",
    type=click.IntRange(min=1),
    help="MSDNet: default DDIM step count T_m written to the manifest; --calibrate and --verify "
    "sample with it [the checkpoint's config].",
)
@click.option(
    "--calibrate",
    type=click.IntRange(min=1),
    help="Choose the threshold on N frames of --data held out of the training range by the run "
    "(its --holdout slice; never validation), by the best mean rank of 5 metrics.",
)
@click.option(
    "--encoder-form",
    type=click.Choice(["rulebook", "pairs"]),
    default="rulebook",
    show_default=True,
    help="encoder.onnx as rulebooks (every kernel tap, zero rows included) or pairs (only the real "
    "neighbour pairs: fewer FLOPs on sparse scans; the same weights).",
)
@one_line_errors
@checks_outputs(out="folder")  # before any work
def main(
    checkpoint: Path,
    out: Path,
    verify: bool,
    data: Path | None,
    dataset: str | None,
    frames: int,
    seed: int,
    threads: int | None,
    sign_key: Path | None,
    threshold: float | None,
    guidance: float | None,
    steps: int | None,
    calibrate: int | None,
    encoder_form: str = "rulebook",
) -> None:
    """Export a student (MSDNet) or R2LDM checkpoint to ONNX graphs and a manifest."""
    import torch

    if threads is not None:
        torch.set_num_threads(threads)
    if data is not None and not (verify or calibrate):
        raise MsdnetError("--data", "only used with --verify or --calibrate")
    if dataset is not None and data is None:
        raise MsdnetError("--dataset", "names the layout of --data; give --data too")
    if given(click.get_current_context(), "frames") and not verify:
        raise MsdnetError("--frames", "only used with --verify (--calibrate takes its own count)")
    if calibrate and threshold is not None:
        raise MsdnetError("--calibrate", "choose either --threshold or --calibrate")
    if calibrate and (data is None or dataset is None):
        raise MsdnetError("--calibrate", "needs --data and --dataset (its training frames are used)")
    check_out(out)
    if sign_key is not None:
        from msdnet.runtime.model.signing import load_private_key

        load_private_key(sign_key)  # a bad key is refused before the export starts
    model, cfg, state = load_for_export(checkpoint)
    if state.kind not in ("student", "r2ldm"):
        raise MsdnetError(checkpoint, f"a {state.kind} checkpoint cannot be exported (student or r2ldm)")
    if guidance is not None:
        if state.kind != "r2ldm":
            raise MsdnetError("--guidance", f"is for R2LDM checkpoints, not a {state.kind}")
        cfg = dataclasses.replace(cfg, r2ldm_guidance=guidance)
        model.step.guidance = guidance  # the step graph (and calibration) sample with it
    if steps is not None:
        cfg = _with_steps(model, cfg, state.kind, steps)
    if calibrate:
        holdout = float(state.dataset.get("holdout", 0.0))
        threshold = _calibrated(model, cfg, dataset, data, calibrate, seed, holdout)
    if threshold is not None:
        cfg = dataclasses.replace(cfg, threshold=threshold)
    frame_list, source = verification_frames(cfg, data, dataset, frames) if verify else (None, "")
    try:
        manifest, report = export_model(
            model, state.kind, cfg, out, str(checkpoint), frame_list, source, seed, threads, sign_key,
            encoder_form,
        )  # fmt: skip
    except VerificationFailed as failed:
        for line in failed.report.lines():
            click.echo(line)
        click.echo(f"verification FAILED: {out} left unchanged", err=True)
        raise SystemExit(EXIT_VERIFY_FAILED) from None
    for line in report.lines() if report else []:
        click.echo(line)
    sizes = ", ".join(f"{g['file']} {g['bytes'] / 1e6:.2f} MB" for g in manifest["graphs"])
    click.echo(f"wrote {out}: {state.kind}, {manifest['parameters']['total']:,} parameters; {sizes}")


def _with_steps(model: Any, cfg: ModelConfig, kind: str, steps: int) -> ModelConfig:
    """``cfg`` (and the model's own copy, which ``predict`` samples with) with the manifest's
    default T_m = ``steps``: the interval becomes m / T_m; the runtime can still choose any."""
    if kind != "student":
        raise MsdnetError("--steps", f"sets MSDNet's T_m, not a {kind}'s sampler")
    if steps > cfg.diffusion.start_step:
        raise MsdnetError("--steps", f"T_m {steps} exceeds the start step m = {cfg.diffusion.start_step}")
    cfg = dataclasses.replace(cfg, diffusion=dataclasses.replace(cfg.diffusion, sample_steps=steps))
    model.cfg = cfg
    return cfg


def _calibrated(
    model: Any, cfg: Any, dataset: str, data: Path, frames: int, seed: int, holdout: float
) -> float:
    """The calibrated threshold, with its table printed."""
    from msdnet.training.recipe.calibrate import calibrate_threshold

    best, rows = calibrate_threshold(model, cfg, dataset, str(data), frames, seed=seed, holdout=holdout)
    where = f"held-out training-range frames (holdout {holdout:g})" if holdout > 0 else "training frames"
    click.echo(f"threshold calibration on {frames} {where} (mean per frame):")
    click.echo("  threshold   CD (m)  MHD (m)  F@0.5 m    JSD  MMD x1e4   points  empty  mean rank")
    for r in rows:
        mark = "  <- chosen" if r.threshold == best else ""
        click.echo(
            f"  {r.threshold:9.2f} {r.cd:8.3f} {r.mhd:8.3f} {r.fscore:8.3f} {r.jsd:6.3f} {1e4 * r.mmd:9.2f}"
            f" {r.points:8.0f} {r.empty:6d} {r.rank:10.2f}{mark}"
        )
    return best
