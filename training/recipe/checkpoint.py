"""Checkpoints without pickle: a folder of safetensors files plus one JSON document.

Layout of a checkpoint folder (``OUT/last``, ``OUT/best``)::

    model.safetensors     weights (``state_dict`` of the bare model, never of a DDP wrapper)
    training.safetensors  tensors of the optimizer and scheduler state (absent when not saved)
    checkpoint.json       format, kind, ModelConfig and TrainConfig (``dataclasses.asdict``),
                          epoch / step bookkeeping, seed, metrics history, teacher path,
                          versions, sha256 of both safetensors files, and the non-tensor part
                          of the optimizer / scheduler state

Nothing is unpickled on load: tensors come from safetensors, everything else from JSON, and
the frozen config dataclasses are rebuilt field by field from their type hints.
A folder is written under a temporary name and swapped in with ``os.replace``; while the
swap runs the previous version sits at ``<name>.old``, which :func:`resolve_checkpoint`
falls back to, so a kill at any moment leaves one complete checkpoint.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import shutil
import tempfile
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import safetensors.torch
import torch

from msdnet.runtime.errors import MsdnetError
from msdnet.training.config import ModelConfig, TrainConfig
from msdnet.training.models.assembly import MODEL_KINDS, build_model

FORMAT = "msdnet-checkpoint"  # value of checkpoint.json "format"
FORMAT_VERSION = 1  # bumped when the layout changes incompatibly
MODEL_FILE = "model.safetensors"
TRAINING_FILE = "training.safetensors"
META_FILE = "checkpoint.json"


@dataclass
class CheckpointState:
    """Everything in ``checkpoint.json`` besides the model config (mutable: the loop updates it)."""

    kind: str  # teacher | student | r2ldm
    train: TrainConfig  # optimisation settings of the run
    epochs: int  # epochs planned for the run (fixes the OneCycleLR length)
    epoch: int = 0  # completed epochs
    step: int = 0  # optimizer steps done in total
    batch_in_epoch: int = 0  # batches done in the unfinished epoch ``epoch`` (0 at a boundary)
    best_val_loss: float | None = None  # lowest validation loss so far
    history: list[dict[str, Any]] = field(default_factory=list)  # one metrics dict per epoch
    teacher: str | None = None  # teacher checkpoint the student / R2LDM was trained against
    dataset: dict[str, Any] = field(default_factory=dict)  # dataset name, root, split, frames
    world_size: int = 1  # processes that trained it (torchrun)
    init: str | None = None  # checkpoint whose weights started the run (msdnet-train --init)
    # the exported model folder the weights were read back from (export/recover.py): its
    # teacher's LiDAR branch is in no graph, so it is not trained weights
    recovered_from: str | None = None


# ---------------------------------------------------------------- config <-> JSON


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """A (nested) config dataclass as plain JSON types (tuples become lists)."""
    return dataclasses.asdict(cfg)


def config_diff(saved: Any, current: Any, ignore: tuple[str, ...] = ()) -> list[str]:
    """``"<field> <saved> (now <current>)"`` for each top-level field of two configs that differs."""
    a, b = config_to_dict(saved), config_to_dict(current)
    return [f"{k} {a[k]!r} (now {b[k]!r})" for k in a if k not in ignore and a[k] != b.get(k)]


def _convert(tp: Any, value: Any, where: str) -> Any:
    """Coerce a JSON value to the annotated type ``tp`` (dataclasses, tuples, optionals)."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return dataclass_from_dict(tp, value, where)  # type: ignore[arg-type]
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _convert(args[0], value, where) if len(args) == 1 else value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise MsdnetError(None, f"{where}: expected a list, got {type(value).__name__}")
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, where) for v in value)
        if len(args) != len(value):
            raise MsdnetError(None, f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_convert(a, v, where) for a, v in zip(args, value, strict=True))
    if tp is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if tp in (int, str, bool) and not isinstance(value, tp):
        raise MsdnetError(None, f"{where}: expected {tp.__name__}, got {value!r}")
    return value


def dataclass_from_dict(cls: type, data: Any, where: str = "config") -> Any:
    """Rebuild the frozen dataclass ``cls`` (and nested ones) from :func:`config_to_dict` output.

    Unknown keys are an error (a config from another version); missing keys take defaults.
    """
    if not isinstance(data, dict):
        raise MsdnetError(None, f"{where}: expected an object for {cls.__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise MsdnetError(None, f"{where}: unknown {cls.__name__} fields {unknown}")
    kwargs = {k: _convert(hints[k], v, f"{where}.{k}") for k, v in data.items()}
    try:
        return cls(**kwargs)
    except TypeError as err:
        raise MsdnetError(None, f"{where}: {err}") from None


# ---------------------------------------------------------------- state trees <-> JSON + tensors


def split_tensors(obj: Any, tensors: dict[str, torch.Tensor], prefix: str) -> Any:
    """JSON-able copy of ``obj`` with every tensor moved into ``tensors`` under a dotted key.

    Encodes what JSON lacks: ``{"__tensor__": key}``, ``{"__tuple__": [...]}`` and, for dicts
    whose keys are not all strings (optimizer state is keyed by parameter index),
    ``{"__items__": [[key, value], ...]}``.
    """
    if isinstance(obj, torch.Tensor):
        tensors[prefix] = obj.detach().cpu().contiguous()
        return {"__tensor__": prefix}
    if isinstance(obj, dict):
        if all(isinstance(k, str) and not k.startswith("__") for k in obj):
            return {k: split_tensors(v, tensors, f"{prefix}.{k}") for k, v in obj.items()}
        return {"__items__": [[k, split_tensors(v, tensors, f"{prefix}.{k}")] for k, v in obj.items()]}
    if isinstance(obj, tuple):
        return {"__tuple__": [split_tensors(v, tensors, f"{prefix}.{i}") for i, v in enumerate(obj)]}
    if isinstance(obj, list):
        return [split_tensors(v, tensors, f"{prefix}.{i}") for i, v in enumerate(obj)]
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    raise TypeError(f"cannot store {type(obj).__name__} at {prefix} without pickle")


def join_tensors(obj: Any, tensors: dict[str, torch.Tensor]) -> Any:
    """Inverse of :func:`split_tensors`."""
    if isinstance(obj, dict):
        if "__tensor__" in obj:
            return tensors[obj["__tensor__"]]
        if "__tuple__" in obj:
            return tuple(join_tensors(v, tensors) for v in obj["__tuple__"])
        if "__items__" in obj:
            return {k: join_tensors(v, tensors) for k, v in obj["__items__"]}
        return {k: join_tensors(v, tensors) for k, v in obj.items()}
    if isinstance(obj, list):
        return [join_tensors(v, tensors) for v in obj]
    return obj


# ---------------------------------------------------------------- files


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def versions() -> dict[str, str]:
    """Versions recorded in every checkpoint."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        msdnet_version = version("msdnet")
    except PackageNotFoundError:
        msdnet_version = "unknown"
    return {
        "msdnet": msdnet_version,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "safetensors": version("safetensors"),
        "python": platform.python_version(),
    }


def _swap_in(tmp: Path, folder: Path, meta: dict[str, Any], files: list[str]) -> None:
    """Write ``meta`` into the temporary folder ``tmp``, sync it and ``files``, and put it in place of
    ``folder``; meanwhile the previous version sits at ``<folder>.old`` (see resolve_checkpoint)."""
    (tmp / META_FILE).write_text(json.dumps(meta, indent=1))
    for name in [*files, META_FILE]:
        _fsync(tmp / name)
    old = folder.with_name(folder.name + ".old")
    if folder.exists():  # else a kill mid-swap left ``old`` as the only copy: keep it
        shutil.rmtree(old, ignore_errors=True)
        os.replace(folder, old)
    os.replace(tmp, folder)
    shutil.rmtree(old, ignore_errors=True)


def save_checkpoint(
    folder: str | Path,
    model: torch.nn.Module,
    cfg: ModelConfig,
    state: CheckpointState,
    optimizer: torch.optim.Optimizer | None = None,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
    ema: dict[str, torch.Tensor] | None = None,
) -> Path:
    """Write ``folder`` atomically (temporary folder beside it, then rename); returns it.

    model: the bare module (unwrap DDP first); its ``state_dict`` goes to model.safetensors.
    ema: the EMA of the trainable weights by parameter name (training/recipe/loop.py), kept with the
    optimizer state in training.safetensors (``ema.<name>``) so a resume continues it.
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    try:
        safetensors.torch.save_model(model, str(tmp / MODEL_FILE))
        files = {MODEL_FILE: _sha256(tmp / MODEL_FILE)}
        training_json: dict[str, Any] = {}
        if optimizer is not None or scheduler is not None:
            tensors: dict[str, torch.Tensor] = {}
            if optimizer is not None:
                training_json["optimizer"] = split_tensors(optimizer.state_dict(), tensors, "opt")
            if scheduler is not None:
                training_json["scheduler"] = split_tensors(scheduler.state_dict(), tensors, "sch")
            if ema is not None:
                training_json["ema"] = sorted(ema)
                tensors.update({f"ema.{k}": v.detach().contiguous() for k, v in ema.items()})
            safetensors.torch.save_file(tensors, str(tmp / TRAINING_FILE))
            files[TRAINING_FILE] = _sha256(tmp / TRAINING_FILE)
        meta = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "kind": state.kind,
            "model_config": config_to_dict(cfg),
            "train_config": config_to_dict(state.train),
            "state": {
                k: getattr(state, k)
                for k in (
                    "epochs",
                    "epoch",
                    "step",
                    "batch_in_epoch",
                    "best_val_loss",
                    "history",
                    "teacher",
                    "dataset",
                    "world_size",
                    "init",
                    "recovered_from",
                )
            },
            "seed": state.train.seed,
            "rng": "reseeded every step from (seed, rank, step); see training/recipe/loop.py",
            "training": training_json,
            "files": files,
            "versions": versions(),
        }
        _swap_in(tmp, folder, meta, list(files))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def _relative(path: str | None) -> str | None:
    """An absolute path as relative to the working directory (POSIX separators); others as given."""
    if not path or not os.path.isabs(path):
        return path
    return Path(os.path.relpath(path)).as_posix()


def publish_checkpoint(src: str | Path, dst: str | Path) -> tuple[Path, str]:
    """Copy checkpoint ``src`` to ``dst`` as weights and ``checkpoint.json`` only: no optimizer,
    scheduler or EMA state (``training.safetensors``), so that it is small enough to commit.

    ``dst`` is written atomically (temporary folder beside it, then rename) and replaces an earlier
    copy; its ``checkpoint.json`` records ``published_from`` (``src``), and its paths (teacher,
    init, dataset root) relative to the working directory, so that no machine's path is committed.
    Such a folder loads, exports and starts ``--init`` / ``--teacher`` runs like ``src``; it cannot
    be ``--resume``d.
    Returns (dst, sha256 of its model.safetensors).
    """
    folder, meta = read_meta(src)
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.", suffix=".tmp", dir=dst.parent))
    try:
        shutil.copyfile(folder / MODEL_FILE, tmp / MODEL_FILE)
        meta = {**meta, "training": {}, "files": {MODEL_FILE: meta["files"][MODEL_FILE]}}
        meta["published_from"] = _relative(str(src))
        state = meta["state"] = dict(meta["state"])
        for key in ("teacher", "init", "recovered_from"):  # no path of this machine in a commit
            state[key] = _relative(state.get(key))
        if isinstance(state.get("dataset"), dict) and "root" in state["dataset"]:
            state["dataset"] = {**state["dataset"], "root": _relative(state["dataset"]["root"])}
        _swap_in(tmp, dst, meta, [MODEL_FILE])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dst, meta["files"][MODEL_FILE]


def resolve_checkpoint(path: str | Path) -> Path:
    """The checkpoint folder for ``path``: the folder, a file in it, or its ``.old`` twin."""
    path = Path(path)
    if path.is_file() and path.name in (META_FILE, MODEL_FILE):
        path = path.parent
    if not (path / META_FILE).is_file():
        old = path.with_name(path.name + ".old")
        if (old / META_FILE).is_file():
            return old
        if not path.exists():
            raise MsdnetError(path, "no such checkpoint")
        raise MsdnetError(path, f"not a checkpoint folder (no {META_FILE})")
    return path


def read_meta(path: str | Path) -> tuple[Path, dict[str, Any]]:
    """(folder, parsed checkpoint.json) after checking format and file hashes."""
    folder = resolve_checkpoint(path)
    try:
        meta = json.loads((folder / META_FILE).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MsdnetError(folder / META_FILE, f"unreadable: {err}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise MsdnetError(folder / META_FILE, f"not an {FORMAT} file")
    if meta.get("format_version") != FORMAT_VERSION:
        raise MsdnetError(
            folder / META_FILE,
            f"format version {meta.get('format_version')}, this msdnet reads {FORMAT_VERSION}",
        )
    if meta.get("kind") not in MODEL_KINDS:
        raise MsdnetError(folder / META_FILE, f"unknown model kind {meta.get('kind')!r}")
    for name, digest in meta.get("files", {}).items():
        file = folder / name
        if not file.is_file():
            raise MsdnetError(file, "missing")
        if _sha256(file) != digest:
            raise MsdnetError(file, "sha256 differs from checkpoint.json (corrupt or replaced)")
    return folder, meta


def read_checkpoint(path: str | Path) -> tuple[Path, ModelConfig, CheckpointState]:
    """(folder, ModelConfig, CheckpointState) of a checkpoint, without building the model."""
    folder, meta = read_meta(path)
    where = str(folder / META_FILE)
    cfg = dataclass_from_dict(ModelConfig, meta.get("model_config"), f"{where}: model_config")
    train = dataclass_from_dict(TrainConfig, meta.get("train_config"), f"{where}: train_config")
    try:
        state = CheckpointState(kind=meta["kind"], train=train, **meta["state"])
    except (KeyError, TypeError) as err:
        raise MsdnetError(folder / META_FILE, f"bad state: {err}") from None
    return folder, cfg, state


def load_checkpoint(path: str | Path) -> tuple[torch.nn.Module, ModelConfig, CheckpointState]:
    """(model with weights loaded, in eval mode; ModelConfig; CheckpointState).

    The model is rebuilt with ``build_model(kind, cfg)``; a student or R2LDM checkpoint holds
    its frozen teacher's weights too, so it loads on its own.
    """
    folder, cfg, state = read_checkpoint(path)
    model = build_model(state.kind, cfg)
    load_weights(model, folder / MODEL_FILE)
    model.eval()
    return model, cfg, state


def load_weights(model: torch.nn.Module, file: Path) -> None:
    """Load model.safetensors into ``model`` strictly; a mismatch names the first keys."""
    try:
        missing, unexpected = safetensors.torch.load_model(model, str(file), strict=False)
    except (RuntimeError, OSError, ValueError) as err:
        raise MsdnetError(file, f"cannot load weights: {str(err).splitlines()[0]}") from None
    if missing or unexpected:
        raise MsdnetError(
            file,
            f"weights do not fit the model: missing {sorted(missing)[:3]}, "
            f"unexpected {sorted(unexpected)[:3]}",
        )


def load_training_state(
    path: str | Path,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
    ema: dict[str, torch.Tensor] | None = None,
) -> None:
    """Restore optimizer (and scheduler, and the weights' EMA into ``ema`` in place) state saved
    by :func:`save_checkpoint`."""
    folder, meta = read_meta(path)
    training = meta.get("training", {})
    if "optimizer" not in training:
        raise MsdnetError(folder, "holds no optimizer state (cannot resume from it)")
    tensors = safetensors.torch.load_file(str(folder / TRAINING_FILE))
    optimizer.load_state_dict(join_tensors(training["optimizer"], tensors))
    if scheduler is not None and "scheduler" in training:
        scheduler.load_state_dict(join_tensors(training["scheduler"], tensors))
    if ema is not None:
        if sorted(ema) != training.get("ema"):
            raise MsdnetError(folder, "holds no EMA of these weights (trained without --ema?)")
        for k, v in ema.items():
            v.copy_(tensors[f"ema.{k}"])
