"""Argument checks every ``msdnet-bench`` command makes before it measures anything.

A benchmark that runs for minutes must not fail at the end on something it could have seen at
the start; these checks are one ``MsdnetError`` line each, naming the option:

- :func:`check_model_folder`: an exported model folder as ``msdnet-infer`` checks it (manifest,
  graph hashes, the encoder form against its graph, a signature when asked) and of an expected
  kind (MSDNet's student, R2LDM), before any session is built;
- :func:`check_folder` / :func:`check_file`: an input that exists and is what it must be;
- :func:`check_preset`: a model preset by name.

Outputs are checked by ``io.atomic.checks_outputs`` (a file where a folder is written, an
unwritable place).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from msdnet.runtime.errors import MsdnetError

PRESETS = ("tiny", "lite", "paper", "paper-width")  # training.config.MODEL_PRESETS, named torch-free
KIND_NAMES = {"student": "an MSDNet (student) model", "r2ldm": "an R2LDM model"}


def check_folder(flag: str, path: Path) -> Path:
    """``path`` is an existing folder; MsdnetError naming ``flag`` otherwise."""
    if not path.exists():
        raise MsdnetError(flag, f"{path}: no such folder")
    if not path.is_dir():
        raise MsdnetError(flag, f"{path}: not a folder")
    return path


def check_file(flag: str, path: Path) -> Path:
    """``path`` is an existing file (or folder: a checkpoint may be either); MsdnetError otherwise."""
    if not path.exists():
        raise MsdnetError(flag, f"{path}: no such file or folder")
    return path


def check_model_folder(flag: str, path: Path, kinds: Sequence[str] = ("student", "r2ldm")) -> Any:
    """The checked ``Artifact`` of the exported folder ``path``, whose kind is one of ``kinds``
    (a published R2LDM with its own sampler counts as ``r2ldm``); MsdnetError naming ``flag``."""
    from msdnet.runtime.model.artifact import load_artifact

    try:
        artifact = load_artifact(path)
    except MsdnetError as err:  # named after the option, and the graph inside the folder
        inside = err.path is not None and Path(err.path).parts[: len(path.parts)] == path.parts
        raise MsdnetError(flag, str(err) if inside else f"{path / str(err.path)}: {err.cause}") from None
    if artifact.kind not in kinds:
        want = " or ".join(KIND_NAMES.get(k, k) for k in kinds)
        held = KIND_NAMES.get(artifact.kind, artifact.kind)
        raise MsdnetError(flag, f"{path} holds {held}, expected {want}")
    return artifact


def check_preset(flag: str, preset: str) -> str:
    """``preset`` is a model preset; MsdnetError naming ``flag`` and the presets otherwise."""
    if preset not in PRESETS:
        raise MsdnetError(flag, f"unknown preset {preset!r} (one of {', '.join(PRESETS)})")
    return preset
