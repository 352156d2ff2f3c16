"""Read an exported model's torch weights back out of its ONNX graphs: a checkpoint again.

A model folder (``msdnet-export`` output) holds every weight the radar path uses, but not always
under its torch name: the exporter's constant folding turns GroupNorm affines into ``onnx::Mul_*``
/ ``onnx::Add_*`` tensors of shape (C, 1, 1) and the sparse-conv kernels into transposed
``onnx::MatMul_*`` matrices. :func:`recover_model` finds where every element went without knowing
those rules: it exports a *probe* model of the same config whose weights are the element indices
themselves (``BASE + i``, exact in float32), so each folded initializer of the probe export
names, element by element, the weight it came from; the shipped graph's initializer read by the
same node input (node names are scoped and stable; initializer names are not where the exporter
merged equal tensors) then gives that element's value. The result is checked by exporting the recovered model
again: every initializer of every graph must equal the shipped one byte for byte.

What no graph holds is set to zeros (a committed checkpoint then stores it in almost no space)
and is listed (``Recovered.absent``): for a
student, the frozen teacher's LiDAR encoder and S2D (the distillation target of full student
training, which a recovered checkpoint therefore cannot do; ``--distill`` and ``--head-only``
runs do not need it).

``msdnet-export recover MODEL_DIR --out CKPT [--dataset D --data ROOT --holdout H]``:
with a dataset the checkpoint also records the training range and selection slice the model was
trained with (``--holdout``: the run's, 0.15 by default as in ``msdnet-train``), so that
``msdnet-bench steps --split select --checkpoint CKPT`` scores the same held-out frames.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import onnx
import torch
from onnx import numpy_helper

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.model.artifact import read_manifest
from msdnet.training.config import ModelConfig, TrainConfig
from msdnet.training.models.assembly import build_model
from msdnet.training.nn.head import Up2x, up_export_style
from msdnet.training.recipe.checkpoint import CheckpointState, dataclass_from_dict, save_checkpoint

BASE = 2**20  # first probe index: far above the small integer constants a graph holds
LIMIT = 2**24  # float32 holds every integer below this exactly


@dataclass(frozen=True)
class Recovered:
    """A model rebuilt from an artifact folder."""

    model: torch.nn.Module  # weights read back, eval mode
    cfg: ModelConfig  # the manifest's config
    kind: str  # student | r2ldm
    elements: int  # weight elements read back from the graphs
    absent: tuple[str, ...]  # state_dict prefixes no graph holds (set to zeros)


Slots = dict[tuple[str, int], str]  # (node name, input slot) -> the initializer it reads


def _read_graph(path: Path) -> tuple[dict[str, np.ndarray], Slots]:
    """(initializers by name, slots) of one ONNX file. The exporter reads merged equal tensors (a
    fresh model's GroupNorm affines are all ones) through Identity nodes: slots see through them."""
    graph = onnx.load(str(path)).graph
    source = {i.name: i.name for i in graph.initializer}
    for n in graph.node:  # Identity(initializer): the exporter's merged copies
        if n.op_type == "Identity" and n.input[0] in source:
            source[n.output[0]] = source[n.input[0]]
    slots = {
        (n.name, k): source[x]
        for n in graph.node
        if n.op_type != "Identity"
        for k, x in enumerate(n.input)
        if x in source
    }
    return {i.name: numpy_helper.to_array(i) for i in graph.initializer}, slots


def _first_reader(slots: Slots) -> dict[str, tuple[str, int]]:
    """initializer name -> the first (node name, input slot) reading it."""
    first: dict[str, tuple[str, int]] = {}
    for slot, name in slots.items():
        first.setdefault(name, slot)
    return first


def _up_style(root: Path) -> str:
    """How the folder's head graph up-samples (``Up2x.export_style``): ``conv_transpose`` as this
    exporter writes it, ``depth_to_space`` (1x1x1 conv + an 8-D Transpose) in older folders."""
    head = root / "recon_head.onnx"
    if not head.is_file():
        return Up2x.export_style
    ops = {n.op_type for n in onnx.load(str(head), load_external_data=False).graph.node}
    return "conv_transpose" if "ConvTranspose" in ops else "depth_to_space"


def encoder_form(manifest: dict) -> str:
    """The encoder form a manifest records (``encoder_form``; absent: the rulebook form)."""
    return str(manifest.get("encoder_form", "rulebook"))


def _export(
    model: torch.nn.Module, kind: str, cfg: ModelConfig, folder: Path, style: str, form: str = "rulebook"
) -> dict[str, tuple[dict[str, np.ndarray], dict[str, tuple[str, int]]]]:
    """file -> (initializers, the first reader of each) of ``model``'s export, its head's
    up-sampling exported in ``style``, its encoder in ``form`` (the manifest's ``encoder_form``)."""
    from msdnet.export.graphs import export_all

    with up_export_style(style):
        export_all(model, kind, cfg, folder, form)
    graphs = {p.name: _read_graph(p) for p in sorted(folder.glob("*.onnx"))}
    return {file: (inits, _first_reader(slots)) for file, (inits, slots) in graphs.items()}


def _float_entries(model: torch.nn.Module) -> list[tuple[str, torch.Tensor]]:
    return [(k, v) for k, v in model.state_dict().items() if v.is_floating_point() and v.numel() > 0]


def _module_of(key: str) -> str:
    """``teacher.encoder.subm.0.conv.weight`` -> ``teacher.encoder``; heads keep one level more."""
    parts = key.split(".")
    return ".".join(parts[: 4 if parts[1:2] == ["head"] else 2])


def recover_model(root: str | Path) -> Recovered:
    """The torch model of the exported folder ``root``, its weights read back (module docstring)."""
    root = Path(root)
    manifest = read_manifest(root)
    kind = manifest.get("model_kind")
    if kind not in ("student", "r2ldm"):
        raise MsdnetError(root / "manifest.json", f"cannot recover a {kind!r} model")
    cfg = dataclass_from_dict(ModelConfig, manifest.get("config"), f"{root / 'manifest.json'}: config")
    torch.manual_seed(0)
    model, probe = build_model(kind, cfg).eval(), build_model(kind, cfg).eval()
    entries = _float_entries(probe)
    starts, total = [], BASE
    with torch.no_grad():
        for _, tensor in entries:  # the probe's weights: their own global element index
            starts.append(total)
            index = torch.arange(total, total + tensor.numel(), dtype=torch.float64)
            tensor.copy_(index.reshape(tensor.shape))
            total += tensor.numel()
    if total >= LIMIT:
        raise MsdnetError(root, f"{total - BASE} weight elements: more than the probe can index")
    flat = [np.full(t.numel(), np.nan) for _, t in entries]  # recovered values, NaN = not seen
    style = _up_style(root)
    form = encoder_form(manifest)
    with tempfile.TemporaryDirectory(prefix="msdnet-recover-") as tmp:
        probed = _export(probe, kind, cfg, Path(tmp), style, form)
    for file, (inits, consumers) in probed.items():
        if not (root / file).is_file():
            continue  # an optional graph the folder does not carry
        shipped, slots = _read_graph(root / file)
        for name, index in inits.items():
            if index.dtype != np.float32 or index.size == 0:
                continue
            ix = index.astype(np.float64).ravel()
            if ix.min() < BASE or ix.max() >= total or not np.all(ix == np.round(ix)):
                continue  # a constant of the graph, not a weight
            there = slots.get(consumers.get(name, ("", -1)))
            if there is None or shipped[there].shape != index.shape:
                node = consumers.get(name, ("?", 0))[0]
                raise MsdnetError(root / file, f"weight {name!r} of {node!r} is not this msdnet's export")
            which = np.searchsorted(starts, ix, side="right") - 1  # weight of each element
            values = shipped[there].astype(np.float64).ravel()
            for j in np.unique(which):  # one, or several folded together (a weight and its bias)
                mine = which == j
                pos = (ix[mine] - starts[j]).astype(np.int64)
                seen = ~np.isnan(flat[j][pos])
                if np.any(flat[j][pos][seen] != values[mine][seen]):
                    raise MsdnetError(root / file, f"{entries[j][0]} differs between the graphs")
                flat[j][pos] = values[mine]
    state = model.state_dict()
    absent: set[str] = set()
    elements = 0
    with torch.no_grad():
        for (key, tensor), values in zip(entries, flat, strict=True):
            got = ~np.isnan(values)
            elements += int(got.sum())
            if not got.any():
                absent.add(_module_of(key))
                state[key].zero_()  # no value to recover: zeros, not a random draw
                continue
            if not got.all():
                raise MsdnetError(root, f"{key}: {int((~got).sum())} of {got.size} elements in no graph")
            state[key].copy_(torch.from_numpy(values.reshape(tensor.shape)).to(state[key].dtype))
    _check_same(model, kind, cfg, root, style, form)
    return Recovered(model, cfg, kind, elements, tuple(sorted(absent)))


def _check_same(
    model: torch.nn.Module, kind: str, cfg: ModelConfig, root: Path, style: str, form: str
) -> None:
    """Export ``model`` again: every initializer of each graph the folder has must be the same bytes."""
    with tempfile.TemporaryDirectory(prefix="msdnet-recover-") as tmp:
        again = _export(model, kind, cfg, Path(tmp), style, form)
    for file, (inits, consumers) in again.items():
        if not (root / file).is_file():
            continue
        shipped, slots = _read_graph(root / file)
        for name, value in inits.items():
            there = slots.get(consumers.get(name, ("", -1)))
            if there is None or shipped[there].tobytes() != value.tobytes():
                raise MsdnetError(root / file, f"re-exported initializer {name!r} differs: not recovered")


def split_record(dataset: str, data: Path, cfg: ModelConfig, holdout: float) -> dict[str, object]:
    """The ``state.dataset`` record ``msdnet-train`` writes: the fitted range and the selection slice
    (first id, last id, count) of ``data`` under ``holdout``."""
    from msdnet.training.data.datasets import make_splits

    fit, select = make_splits(dataset, data, cfg, holdout=holdout)
    return {
        "name": dataset,
        "root": str(Path(data).resolve()),
        "train_frames": [fit.frame_ids[0], fit.frame_ids[-1], len(fit)],
        "val_frames": [select.frame_ids[0], select.frame_ids[-1], len(select)],
        "holdout": holdout,
    }


def recover_checkpoint(
    root: str | Path, out: str | Path, dataset: dict[str, object] | None = None
) -> tuple[Path, Recovered]:
    """Write the recovered model of ``root`` as a checkpoint folder ``out`` (``dataset``: the split
    record to keep, :func:`split_record`); -> (out, what was read)."""
    rec = recover_model(root)
    state = CheckpointState(
        kind=rec.kind, train=TrainConfig(), epochs=0, recovered_from=str(root), dataset=dataset or {}
    )
    return save_checkpoint(out, rec.model, rec.cfg, state), rec


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("model_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), required=True, help="checkpoint folder to write")
@click.option("--dataset", help="Record the model's training split on this dataset (sim, astyx, vod).")
@click.option("--data", type=click.Path(path_type=Path), help="--dataset root.")
@click.option("--holdout", type=float, default=0.15, show_default=True, help="The training run's --holdout.")
@one_line_errors
def main(model_dir: Path, out: Path, dataset: str | None, data: Path | None, holdout: float) -> None:
    """Rebuild a checkpoint from the exported model MODEL_DIR (its ONNX graphs' weights)."""
    if out.exists():
        raise MsdnetError(out, "exists: choose another --out")
    if (dataset is None) != (data is None):
        raise MsdnetError("--dataset", "--dataset and --data go together")
    split = None
    if dataset is not None and data is not None:
        manifest = read_manifest(model_dir)
        cfg = dataclass_from_dict(
            ModelConfig, manifest.get("config"), f"{model_dir / 'manifest.json'}: config"
        )
        split = split_record(dataset, data, cfg, holdout)
    folder, rec = recover_checkpoint(model_dir, out, split)
    click.echo(
        f"{rec.kind}: {rec.elements:,} weight elements read back from {model_dir}, re-export identical"
        f" -> {folder}; in no graph (zeros): {', '.join(rec.absent) or 'none'}"
    )
