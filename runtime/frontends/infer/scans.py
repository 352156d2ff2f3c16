"""What ``msdnet-infer`` is given, checked before any scan runs: scans, a dataset, the right model.

- ``dataset_layout``: a folder that holds a whole dataset (an Astyx HiRes2019 root, a View-of-Delft
  root, the simulator's output) is named, so that the user is told which ``--dataset`` reads it;
- ``is_scan``: inside a folder, a ``.txt`` counts as a scan only where its first line names
  ``x y z ...`` or holds at least three numbers (a licence, a frame list, a calibration or a label
  file is left alone);
- ``check_columns``: the columns of the scans against the model's input columns; where they do not
  fit, one error for the run that names, by name, the shipped models whose columns fit.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from msdnet.runtime.errors import MsdnetError

TXT_SNIFF_BYTES = 4096  # enough for the first line of any scan's text


def dataset_layout(folder: Path) -> tuple[str, str, Path] | None:
    """-> (``--dataset`` value, what the folder is, the folder of its radar scans) when ``folder``
    holds a whole dataset in a layout ``--dataset`` reads; None otherwise."""
    radar = folder / "radar" / "training" / "velodyne"
    if (folder / "sequences.json").is_file() and radar.is_dir():
        rig = _sim_rig(folder / "sequences.json")
        key = "sim-astyx" if rig == "astyx" else "sim"
        return key, f"the simulator's output ({rig or 'vod'} rig)", radar
    if radar.is_dir() and (folder / "lidar" / "training" / "velodyne").is_dir():
        return "vod", "a View-of-Delft dataset", radar
    if (folder / "radar_6455").is_dir() and (
        (folder / "dataset.json").is_file() or (folder / "lidar_vlp16").is_dir()
    ):
        return "astyx", "an Astyx HiRes2019 dataset", folder / "radar_6455"
    return None


def _sim_rig(path: Path) -> str | None:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    rig = doc.get("rig") if isinstance(doc, dict) else None
    return rig if isinstance(rig, str) else None


def refuse_dataset_folder(folder: Path) -> None:
    """MsdnetError naming the ``--dataset`` to add when ``folder`` is a whole dataset."""
    found = dataset_layout(folder)
    if found is None:
        return
    key, name, radar = found
    raise MsdnetError(
        folder,
        f"is {name}: add --dataset {key} to densify its radar and score it against its "
        f"LiDAR, or give {shown(radar)} to densify the radar scans alone",
    )


def is_scan(path: Path) -> bool:
    """Whether a file found in a folder is a point-cloud scan (only ``.txt`` files are sniffed)."""
    if path.suffix.lower() != ".txt":
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(TXT_SNIFF_BYTES)
    except OSError:
        return True  # unreadable: let the reader say why
    try:
        lines = head.decode("ascii").splitlines()
    except UnicodeDecodeError:
        return False
    first = next((line.split() for line in lines if line.strip()), None)
    if first is None or len(first) < 3:
        return False
    from msdnet.runtime.engine.pointcloud import canonical_column

    if [canonical_column(t) for t in first[:3]] == ["x", "y", "z"]:
        return True
    return all(_is_number(t) for t in first)


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def shown(path: Path) -> str:
    """``path`` relative to the working folder where it lies inside it, else absolute."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def model_shown(folder: Path) -> str:
    """A shipped model by its name (what ``--model`` takes from any folder), another by its path."""
    from msdnet.runtime.model.shipped import shipped_name

    return shipped_name(folder) or shown(folder)


def shipped_models_for(columns: Sequence[str], models_root: Path) -> list[Path]:
    """The shipped model folders under ``models_root`` whose input columns the scans hold, the
    full MSDNet models first."""
    fits = []
    for manifest in sorted(models_root.glob("*/manifest.json")):
        try:
            doc = json.loads(manifest.read_text(encoding="utf-8"))
            wanted = doc["input"]["columns"]
            kind = doc.get("model_kind", "")
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if set(wanted) <= set(columns):
            fits.append((kind == "r2ldm", len(manifest.parent.name), manifest.parent))
    return [folder for *_, folder in sorted(fits)]


def check_columns(
    what: str, columns: Sequence[str], model_dir: Path, model_columns: Sequence[str], models_root: Path
) -> None:
    """MsdnetError, one line for the run, when the scans of ``what`` lack a column of the model;
    it names the shipped models that read these scans."""
    missing = [c for c in model_columns if c not in columns]
    if not missing:
        return
    fits = [f for f in shipped_models_for(columns, models_root) if f.resolve() != model_dir.resolve()]
    if fits:
        also = f" (so do {', '.join(model_shown(f) for f in fits[1:])})" if len(fits) > 1 else ""
        advice = f"use --model {model_shown(fits[0])}, which reads these columns{also}"
    else:
        advice = "no shipped model reads them: train one on your own data (docs/own-data.md)"
    raise MsdnetError(
        what,
        f"the scans have columns {' '.join(columns)}; the model {model_shown(model_dir)} needs "
        f"{' '.join(model_columns)} ({', '.join(missing)} missing); {advice}",
    )


def check_scan_columns(
    files: Sequence[Path],
    bin_columns: tuple[str, ...] | None,
    model_dir: Path,
    model_columns: Sequence[str],
    models_root: Path,
) -> None:
    """Read the first scan of each folder and format among ``files`` and check its columns
    (``check_columns``), so that a whole batch the model cannot read stops in one line before any
    scan runs; a scan that cannot be read is left to the run, which reports it."""
    from msdnet.runtime.io.files import read_cloud
    from msdnet.runtime.io.layouts import columns_for

    groups: dict[tuple[Path, str], list[Path]] = {}
    for f in files:
        groups.setdefault((f.parent, f.suffix.lower()), []).append(f)
    for (folder, suffix), members in groups.items():
        try:
            cloud = read_cloud(members[0], columns=columns_for(members[0], bin_columns))
        except MsdnetError:
            continue
        what = str(members[0]) if len(members) == 1 else f"{folder} ({len(members)} {suffix} scans)"
        check_columns(what, cloud.columns, model_dir, model_columns, models_root)
