"""Re-export a model folder's graphs with this msdnet's exporter, everything it was calibrated with kept.

``msdnet-export refresh MODEL [--out DIR]``: the weights are read back out of MODEL's
graphs (``export.recover``, which checks them by an identical re-export of the old form) and
exported again as this exporter writes them (e.g. the head's 2x up-sampling as one
``ConvTranspose`` instead of a 1x1x1 conv and an 8-D ``Transpose``), the encoder in the form the
manifest records (``encoder_form``: rulebook or pairs). The new folder keeps the old
manifest's threshold, gate, calibration records, default step count, source and every other file
(``MODEL.md``, ``LICENSE.md``); only ``graphs``, ``versions`` and ``opset`` change, and a
``refreshed`` record lists the old hashes.

Before anything is written, every graph of the new folder is run beside the old one on the
model's own inputs (``provider_measure.graph_inputs``: a seeded scan through the old pipeline) and
must agree within the export tolerances (``export.verify``), and both pipelines must decode the
same points from that scan. A signed folder is refused (its signature would no longer hold: sign
the refreshed folder again with ``msdnet-export --sign``). MODEL is checked as ``msdnet-infer``
checks it (``runtime.model.artifact.load_artifact``: hashes, plain names, no external data) before
any graph is parsed, and the output's place is checked writable (``io.atomic.check_writable``), so
a bad folder is one line naming the file. The folder is written under a temporary name and renamed
when whole (``export.cli.publish``).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import check_writable, clean_stale_temps, temp_name
from msdnet.runtime.model.artifact import MANIFEST, load_artifact, read_manifest

SIGNATURE = "manifest.sig"
KEPT_FROM_NEW = ("graphs", "versions", "opset")  # manifest fields the re-export decides


@dataclass(frozen=True)
class Refreshed:
    """What :func:`refresh_model` wrote and checked."""

    out: Path  # the refreshed folder
    changed: tuple[str, ...]  # graph files whose bytes changed
    max_rel: float  # largest relative difference of any graph output, new vs old
    points: int  # points both pipelines decoded from the check scan (equal)


def _agree(old_dir: Path, new_dir: Path) -> tuple[float, int]:
    """(largest relative output difference, decoded points) of the two folders on the old
    model's own inputs; MsdnetError when a graph or the decoded points disagree."""
    from msdnet.runtime.engine.pipeline import Pipeline
    from msdnet.runtime.providers.provider_measure import disagreement, graph_inputs, seeded_scan

    old, new = Pipeline.from_dir(old_dir, threads=1), Pipeline.from_dir(new_dir, threads=1)
    worst = 0.0
    for file, feed in graph_inputs(old).items():
        ref = [np.asarray(a) for a in old.sessions[file].run(None, feed)]
        got = [np.asarray(a) for a in new.sessions[file].run(None, feed)]
        names = [o.name for o in old.sessions[file].get_outputs()]
        why = disagreement(got, ref, names)
        if why is not None:
            raise MsdnetError(new_dir / file, f"re-exported graph disagrees with the old one: {why}")
        for a, b in zip(got, ref, strict=True):
            if a.shape == b.shape and a.size and np.issubdtype(b.dtype, np.floating):
                scale = float(np.max(np.abs(b))) or 1.0
                worst = max(worst, float(np.max(np.abs(a.astype(np.float64) - b))) / scale)
    pts = seeded_scan(old, np.random.default_rng(0))  # the scan graph_inputs ran
    a, b = old(pts, seed=0).points, new(pts, seed=0).points
    if a.shape != b.shape or not np.allclose(a, b, atol=1e-4):
        raise MsdnetError(new_dir, f"decodes {len(b)} points where the old folder decodes {len(a)}")
    return worst, len(a)


def refresh_model(root: str | Path, out: str | Path | None = None) -> Refreshed:
    """Re-export ``root`` into ``out`` (default: ``root`` itself, replaced when whole)."""
    from msdnet.export.cli import check_out, publish
    from msdnet.export.graphs import export_all
    from msdnet.export.manifest import build_manifest
    from msdnet.export.recover import encoder_form, recover_model

    root = Path(root)
    out = root if out is None else Path(out)
    if (root / SIGNATURE).exists():
        raise MsdnetError(root / SIGNATURE, "a signed model: refresh it unsigned, then sign it again")
    check_out(out)
    check_writable(out, "folder")  # before any work
    load_artifact(root)  # as msdnet-infer checks it, before onnx parses a graph (external data, ..)
    old_manifest = read_manifest(root)
    try:
        rec = recover_model(root)
    except MsdnetError:
        raise
    except Exception as err:  # onnx / torch errors on a graph that passed the checks above
        cause = " ".join(str(err).split())[:200] or type(err).__name__
        raise MsdnetError(root, f"cannot read the weights back ({type(err).__name__}: {cause})") from None
    out.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_temps(out.parent)
    tmp = out.parent / temp_name(out.name)
    tmp.mkdir()
    try:
        with tempfile.TemporaryDirectory(prefix="msdnet-refresh-") as graphs_dir:
            new_dir = Path(graphs_dir)
            form = encoder_form(old_manifest)  # the encoder stays in the form it was exported in
            params, _ = export_all(rec.model, rec.kind, rec.cfg, new_dir, form)
            source = old_manifest.get("source", "")
            fresh = build_manifest(new_dir, rec.kind, rec.cfg, params, source, encoder_form=form)
            for f in root.iterdir():  # the old folder's files, then the new graphs over its graphs
                if f.is_file() and f.name not in (MANIFEST, SIGNATURE):
                    shutil.copy2(f, tmp / f.name)
            for g in fresh["graphs"]:
                shutil.copy2(new_dir / g["file"], tmp / g["file"])
        manifest: dict[str, Any] = {**old_manifest, **{k: fresh[k] for k in KEPT_FROM_NEW}}
        old_hashes = {g["file"]: g["sha256"] for g in old_manifest.get("graphs", [])}
        changed = tuple(g["file"] for g in fresh["graphs"] if old_hashes.get(g["file"]) != g["sha256"])
        manifest["refreshed"] = {"previous_sha256": old_hashes, "changed": list(changed)}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
        max_rel, points = _agree(root, tmp)
        manifest["refreshed"] |= {"max_rel_vs_previous": max_rel, "check_scan_points": points}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
        publish(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return Refreshed(out, changed, max_rel, points)


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("model", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option(
    "--out", type=click.Path(path_type=Path), help="Write the refreshed folder here [MODEL itself]."
)
@one_line_errors
def main(model: Path, out: Path | None) -> None:
    """Re-export MODEL's graphs with this msdnet (weights, threshold, gate and step count kept)."""
    r = refresh_model(model, out)
    click.echo(
        f"{r.out}: {', '.join(r.changed) or 'no graph'} re-exported; every graph within the export "
        f"tolerances of the old one (max rel {r.max_rel:.1e}), same {r.points} points on the check scan"
    )
