"""``msdnet-export CHECKPOINT --out DIR [--verify]``: checkpoint -> ONNX graphs + manifest.json.

The folder is built under a temporary name next to ``--out`` and renamed into place only when
complete (and, with ``--verify``, only when verification passes), so ``--out`` is always either
the previous artifact or the new one. Exit 1 when verification fails, 2 on bad input.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import click
import numpy as np

from msdnet.runtime.artifact import MANIFEST
from msdnet.runtime.datasets import DATASET_NAMES
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.training.config import ModelConfig

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
    from msdnet.runtime.datasets import open_dataset

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


def publish(tmp: Path, out: Path) -> None:
    """Move the finished folder ``tmp`` to ``out``, replacing a previous artifact there."""
    if out.is_symlink():
        raise MsdnetError(out, "is a symlink; refusing to replace it")
    if not out.exists():
        os.replace(tmp, out)
        return
    if not out.is_dir():
        raise MsdnetError(out, "exists and is not a folder")
    if any(out.iterdir()) and not (out / MANIFEST).is_file():
        raise MsdnetError(out, "folder is not empty and holds no manifest.json; refusing to replace it")
    old = out.with_name(f".{out.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    os.replace(out, old)
    os.replace(tmp, out)
    shutil.rmtree(old, ignore_errors=True)


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("checkpoint", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Artifact folder.")
@click.option("--verify", is_flag=True, help="Compare torch and onnxruntime; fail beyond tolerance.")
@click.option("--data", type=click.Path(path_type=Path), help="Dataset root for --verify frames.")
@click.option("--dataset", type=click.Choice(DATASET_NAMES), help="Layout of --data.")
@click.option("--frames", type=click.IntRange(min=1), default=3, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True, help="Noise seed for --verify.")
@one_line_errors
def main(
    checkpoint: Path,
    out: Path,
    verify: bool,
    data: Path | None,
    dataset: str | None,
    frames: int,
    seed: int,
) -> None:
    """Export a student (MSDNet) or R2LDM checkpoint to ONNX graphs and a manifest."""
    import torch

    from msdnet.export.graphs import export_all
    from msdnet.export.manifest import build_manifest, write_manifest
    from msdnet.export.verify import verify_artifact
    from msdnet.training.checkpoint import load_checkpoint

    if data is not None and not verify:
        raise MsdnetError("--data", "only used with --verify")
    model, cfg, state = load_checkpoint(checkpoint)
    if state.kind not in ("student", "r2ldm"):
        raise MsdnetError(checkpoint, f"a {state.kind} checkpoint cannot be exported (student or r2ldm)")
    frame_list, source = verification_frames(cfg, data, dataset, frames) if verify else ([], "")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        torch.manual_seed(seed)
        params, _ = export_all(model, state.kind, cfg, tmp)
        manifest = build_manifest(tmp, state.kind, cfg, params, str(checkpoint))
        write_manifest(tmp, manifest)
        if verify:
            report = verify_artifact(model, state.kind, cfg, tmp, frame_list, source, seed)
            for line in report.lines():
                click.echo(line)
            if not report.ok:
                click.echo(f"verification FAILED: {out} left unchanged", err=True)
                raise SystemExit(EXIT_VERIFY_FAILED)
            manifest["verification"] = report.to_dict()
            write_manifest(tmp, manifest)
        _fsync_folder(tmp)
        publish(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    sizes = ", ".join(f"{g['file']} {g['bytes'] / 1e6:.2f} MB" for g in manifest["graphs"])
    click.echo(
        f"wrote {out}: {state.kind}, {manifest['parameters']['total']:,} parameters; {sizes}"
    )
