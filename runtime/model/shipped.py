"""The models shipped inside the package (``msdnet.models``), found by name from any folder.

``find_model("astyx-lite")`` is the shipped folder of that name, wherever the package is installed;
a path that exists is taken as it is (a folder written by ``msdnet-export``), so a local folder
that happens to share a shipped model's name wins. A bare name that is neither a folder here nor
a shipped model is refused in one line that lists the shipped names.
"""

from __future__ import annotations

from pathlib import Path

import msdnet.models
from msdnet.runtime.errors import MsdnetError

SHIPPED_DIR = Path(msdnet.models.__file__).resolve().parent  # one folder per shipped model
DEFAULT_MODEL = "sim-lite"  # what the front-ends run when no --model is given
MANIFEST = "manifest.json"


def shipped_names() -> tuple[str, ...]:
    """The names of the shipped models (folders of ``msdnet.models`` with a manifest), sorted."""
    return tuple(sorted(p.parent.name for p in SHIPPED_DIR.glob(f"*/{MANIFEST}") if p.is_file()))


def shipped_name(folder: str | Path) -> str | None:
    """The shipped name of ``folder`` when it is a shipped model's folder, else None."""
    try:
        path = Path(folder).resolve()
    except OSError:
        return None
    return path.name if path.parent == SHIPPED_DIR and (path / MANIFEST).is_file() else None


def _is_bare_name(text: str) -> bool:
    return bool(text) and Path(text).name == text and text not in (".", "..")


def find_model(model: str | Path) -> Path:
    """The model folder ``model`` names: a path that exists, else the shipped model of that name.

    MsdnetError when a bare name is neither; a missing path is returned as it is, for the
    artifact's checks to name."""
    path = Path(model)
    if path.exists() or path.is_symlink() or not _is_bare_name(str(model)):
        return path
    shipped = SHIPPED_DIR / str(model)
    if (shipped / MANIFEST).is_file():
        return shipped
    names = ", ".join(shipped_names()) or "none"
    raise MsdnetError(
        str(model),
        f"no such model folder and no shipped model of that name; shipped models: {names} "
        "(or give the path of a folder written by msdnet-export)",
    )
