"""The model a front-end runs and the options checked against it (``msdnet-infer``, ``msdnet-node``).

- ``resolve_model``: ``--model``, a folder or a shipped model's name (``astyx-lite``), else the
  shipped ``sim-lite`` (``BUNDLED_MODEL``);
- ``check_model_options``: the model (hashes, ``--trusted-key`` signature), ``--provider``,
  ``--threshold`` and ``--steps``, checked before any input is read; each problem is one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model.shipped import DEFAULT_MODEL, SHIPPED_DIR, find_model

BUNDLED_MODEL = SHIPPED_DIR / DEFAULT_MODEL  # shipped default model


def resolve_model(model: str | Path | None) -> Path:
    """--model (a folder, or a shipped model's name), or the bundled model; MsdnetError when
    neither exists, an unknown name listing the shipped ones."""
    if model is not None:
        return find_model(model)
    if (BUNDLED_MODEL / "manifest.json").is_file():
        return BUNDLED_MODEL
    raise MsdnetError(
        "--model",
        f"no model given and no bundled model at {BUNDLED_MODEL}; "
        "pass --model DIR (a folder written by msdnet-export)",
    )


def check_model_options(
    model_dir: Path, trusted_key: Path | None, provider: str, threshold: float | None, steps: int | None
) -> Any:
    """Load the artifact (hashes, signature) and check ``--provider``, ``--threshold`` and
    ``--steps`` against it; -> the ``Artifact``. Each problem is one ``MsdnetError`` line."""
    from msdnet.runtime.model.artifact import load_artifact
    from msdnet.runtime.providers.session import resolve_providers
    from msdnet.runtime.spec.ddim import timesteps

    artifact = load_artifact(model_dir, trusted_key)  # refuse a bad model before any input
    resolve_providers(provider)
    if threshold is not None and not 0.0 < threshold < 1.0:
        raise MsdnetError("--threshold", f"must be in (0, 1), got {threshold}")
    try:
        timesteps(artifact.diffusion, steps)
    except ValueError as err:
        raise MsdnetError("--steps", str(err)) from None
    return artifact
