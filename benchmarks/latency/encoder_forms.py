"""``msdnet-bench encoders``: the encoder alone in its two forms (rulebook, pairs) on the same real
scans, interleaved.

    msdnet-bench encoders --preset paper-width --data DIR [--frames 20]

A radar encoder of the preset's widths (random weights: the time does not depend on them; a
``--model`` folder's own encoder is read back instead when given) is exported in both forms; each
frame of ``--data`` (Astyx layout, validation split) is voxelized once, then every engine runs
both forms on it back to back, the order alternating per frame, once and then ``--repeats`` times.
Printed: per engine, for the first call on each frame (a new input shape, as a sensor's frames
are) and for the calls after it, the median ms of each form and the median over the frames of
pairs / rulebook (paired by frame), and the parity of the outputs. The encoders come from torch and
the exporter, so the command needs the ``train`` extra.
"""

from __future__ import annotations

import importlib.util
import tempfile
import time
from pathlib import Path
from typing import Any

import click
import numpy as np

from msdnet.benchmarks.args import PRESETS
from msdnet.runtime.errors import MsdnetError, one_line_errors


def _encoder(preset: str, model: Path | None) -> tuple[Any, Any]:
    """(radar SparseEncoder, its config): the preset's with Astyx columns, random weights; or
    the ``model`` folder's, read back from its graphs."""
    import torch

    from msdnet.training.config import MODEL_PRESETS
    from msdnet.training.data.datasets import config_for_dataset
    from msdnet.training.nn.encoder import SparseEncoder

    if model is not None:
        from msdnet.export.recover import recover_model

        rec = recover_model(model)
        return rec.model.encoder.eval(), rec.cfg
    cfg = config_for_dataset(MODEL_PRESETS[preset], "astyx")
    torch.manual_seed(0)
    return SparseEncoder(cfg, "radar").eval(), cfg


def check_inputs(data: Path, model: Path | None) -> None:
    """Before torch is imported or anything exported: ``data`` holds Astyx validation frames, and
    ``model`` (when given) is an exported folder whose input columns those frames hold."""
    from msdnet.benchmarks.args import check_folder, check_model_folder
    from msdnet.runtime.io.datasets import open_dataset

    ds = open_dataset("astyx", check_folder("--data", data), split="val")
    if len(ds) == 0:
        raise MsdnetError("--data", f"{data}: no Astyx validation frames")
    if model is None:
        return
    columns = tuple(check_model_folder("--model", model).inputs.columns)
    have = tuple(ds[0].radar.columns)
    missing = [c for c in columns if c not in have]
    if missing:
        raise MsdnetError(
            "--model",
            f"{model} reads columns {' '.join(columns)}; Astyx frames have {' '.join(have)} "
            f"(no {' '.join(missing)}): a model trained on Astyx is needed",
        )


def _time(run: Any, repeats: int) -> tuple[float, float]:
    """(ms of the first call on this input, as a sensor's new frame meets it; median ms of
    ``repeats`` calls after it)."""
    t0 = time.perf_counter()
    run()
    first = time.perf_counter() - t0
    again = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        again.append(time.perf_counter() - t0)
    return first * 1e3, float(np.median(again)) * 1e3


def compare(
    preset: str, data: Path, frames: int, repeats: int, threads: int, model: Path | None = None
) -> dict[str, Any]:
    """Time both forms (module docstring); -> {engine: {"old_ms", "new_ms", "ratio"}, "parity"}."""
    import torch

    from msdnet.export.encoder_pairs import pairs_encoder_model
    from msdnet.export.graphs import example_inputs, export_graph, make_encoder_input, tracing_points
    from msdnet.runtime.engine.pairs import pair_feeds
    from msdnet.runtime.engine.rulebook import batch_coords, build_encoder_rulebooks
    from msdnet.runtime.engine.voxelize import voxelize
    from msdnet.runtime.io.datasets import open_dataset
    from msdnet.runtime.model import onnx_spec
    from msdnet.runtime.providers.openvino_session import OpenVinoSession
    from msdnet.runtime.providers.session import create_session

    enc, cfg = _encoder(preset, model)
    with tempfile.TemporaryDirectory(prefix="msdnet-encoder-forms-") as tmp:
        old_path, new_path = Path(tmp) / "rulebook.onnx", Path(tmp) / "pairs.onnx"
        traced = make_encoder_input([tracing_points(cfg)], cfg.grid, cfg.max_voxels_radar)
        torch.set_num_threads(1)
        export_graph(enc, example_inputs(onnx_spec.ENCODER, cfg, traced), onnx_spec.ENCODER, old_path)
        new_path.write_bytes(pairs_encoder_model(enc).SerializeToString())
        old_bytes, new_bytes = old_path.read_bytes(), new_path.read_bytes()
    engines = {
        "onnxruntime": (
            create_session(old_bytes, "rulebook", "cpu", threads),
            create_session(new_bytes, "pairs", "cpu", threads),
        ),
        "openvino": (OpenVinoSession(old_bytes, threads), OpenVinoSession(new_bytes, threads)),
    }
    ds = open_dataset("astyx", data, split="val")
    times: dict[str, dict[str, list[tuple[float, float]]]] = {e: {"old": [], "new": []} for e in engines}
    worst, voxels = 0.0, []
    for i in range(min(frames, len(ds))):
        pts = np.ascontiguousarray(ds[i].radar.select(cfg.radar_columns).points, np.float32)
        vox = voxelize(pts, cfg.grid, cfg.max_voxels_radar)
        if len(vox.coords) == 0:
            continue
        voxels.append(len(vox.coords))
        rb = build_encoder_rulebooks(batch_coords([vox.coords]), cfg.grid.shape_zyx)
        old = {"voxel_features": vox.features, "subm_rules_0": rb.subm[0].astype(np.int64)}
        for level in range(1, onnx_spec.NUM_DOWN + 1):
            old[f"down_rules_{level}"] = rb.down[level - 1].astype(np.int64)
            old[f"subm_rules_{level}"] = rb.subm[level].astype(np.int64)
        old["bev_coords"] = rb.coords[-1].astype(np.int64)
        new = {"voxel_features": vox.features, **pair_feeds(rb, onnx_spec.NUM_DOWN)}
        ref = engines["onnxruntime"][0].run(None, old)[0]
        got = engines["onnxruntime"][1].run(None, new)[0]
        worst = max(worst, float(np.abs(got - ref).max() / np.abs(ref).max()))
        for e, (s_old, s_new) in engines.items():
            order = [("old", s_old, old), ("new", s_new, new)]
            for form, sess, feeds in order if i % 2 == 0 else order[::-1]:
                times[e][form].append(_time(lambda s=sess, f=feeds: s.run(None, f), repeats))
    out: dict[str, Any] = {"frames": len(voxels), "voxels_median": float(np.median(voxels)), "parity": worst}
    for e, t in times.items():
        old_ms, new_ms = np.asarray(t["old"]), np.asarray(t["new"])  # (frames, 2): first, repeated
        out[e] = {
            f"{k}_{when}": v
            for j, when in enumerate(("first", "repeated"))
            for k, v in (
                ("old_ms", float(np.median(old_ms[:, j]))),
                ("new_ms", float(np.median(new_ms[:, j]))),
                ("ratio", float(np.median(new_ms[:, j] / old_ms[:, j]))),
            )
        }
    return out


@click.command("encoders", context_settings={"help_option_names": ["-h", "--help"]})
@click.option(
    "--preset", type=click.Choice(PRESETS), default="lite", show_default=True, help="Encoder widths and grid."
)
@click.option("--model", type=click.Path(path_type=Path), help="An exported model: its own encoder.")
@click.option("--data", type=click.Path(path_type=Path), required=True, help="Astyx dataset root.")
@click.option("--frames", type=click.IntRange(min=1), default=20, show_default=True)
@click.option("--repeats", type=click.IntRange(min=1), default=3, show_default=True)
@click.option("--threads", type=click.IntRange(min=1), default=2, show_default=True)
@one_line_errors
def encoders_command(
    preset: str, model: Path | None, data: Path, frames: int, repeats: int, threads: int
) -> None:
    """Time the encoder's rulebook and pair forms on the same Astyx scans, interleaved, on
    onnxruntime and OpenVINO. Needs the train extra (torch): pip install 'msdnet[train]'."""
    if importlib.util.find_spec("torch") is None:
        raise MsdnetError("msdnet-bench encoders", "needs torch: pip install 'msdnet[train]'")
    check_inputs(data, model)
    res = compare(preset, data, frames, repeats, threads, model)
    click.echo(
        f"{preset if model is None else model}: {res['frames']} Astyx frames (median "
        f"{res['voxels_median']:.0f} voxels), {threads} threads; pairs vs rulebook max rel "
        f"difference {res['parity']:.1e}"
    )
    for e in ("onnxruntime", "openvino"):
        r = res[e]
        for when in ("first", "repeated"):
            click.echo(
                f"  {e}, {when} call: rulebook {r[f'old_ms_{when}']:.2f} ms, pairs {r[f'new_ms_{when}']:.2f} "
                f"ms, pairs / rulebook {r[f'ratio_{when}']:.2f} (median over frames)"
            )
