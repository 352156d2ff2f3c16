"""``--provider auto``'s cache of picks: where the file is, what a key holds, reading, checking
and writing it.

A pick is keyed by the model's hash, the graph, its threads, the CPU and the onnxruntime and
OpenVINO versions (``openvino bf16`` too for ``auto-bf16``). The file is read once per load and
each entry validated as it is looked up; an entry that does not validate, or a file that cannot be
read or is of another ``CACHE_VERSION``, counts as absent, with a note. Writes merge into the file
atomically. This process keeps every pick it used or made, so later loads skip the file.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import math
import os
import platform
import tempfile
from pathlib import Path
from typing import Any

import onnxruntime as ort

CACHE_VERSION = 4  # 3: a second stream for the head pick, no time budget
_MEMO: dict[str, dict[str, Any]] = {}  # cache key -> entry, this process


def cache_shown(cache: Path) -> str:
    """``cache`` as results documents record it: under ``$XDG_CACHE_HOME`` or ``~`` named so, not by
    the machine's folders."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    for root, name in ((base, "$XDG_CACHE_HOME"), (str(Path.home()), "~")):
        if root and Path(root).is_absolute():
            try:
                return f"{name}/{cache.relative_to(root).as_posix()}"
            except ValueError:
                continue
    return cache.name


def cache_path() -> Path:
    """``$XDG_CACHE_HOME/msdnet/providers.json``; ``~/.cache`` when unset or not absolute."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    root = Path(base) if base and Path(base).is_absolute() else Path.home() / ".cache"
    return root / "msdnet" / "providers.json"


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``, else ``platform``) and logical core count."""
    name = ""
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace").splitlines():
            if line.lower().startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{name or platform.processor() or platform.machine()} x{os.cpu_count()}"


def openvino_version() -> str | None:
    """The installed OpenVINO's version, None when it is not installed."""
    if importlib.util.find_spec("openvino") is None:
        return None
    import openvino as ov

    return str(ov.__version__)


def model_hash(manifest: dict[str, Any]) -> str:
    """sha256 of the manifest (canonical JSON): it lists every graph's sha256 and the gate."""
    return hashlib.sha256(json.dumps(manifest, sort_keys=True).encode()).hexdigest()


def cache_key(manifest: dict[str, Any], graph: str, threads: int | None, precision: str = "f32") -> str:
    ov = openvino_version() or "none"
    parts = [model_hash(manifest), graph, f"threads {threads or 'default'}", cpu_model()]
    if precision != "f32":  # f32 keys stay as they were, so existing caches still hold
        parts.append(f"openvino {precision}")
    return " | ".join([*parts, f"onnxruntime {ort.__version__}", f"openvino {ov}"])


def load_cache(path: Path) -> tuple[dict[str, Any], str | None]:
    """The cache file's entries, each still to validate (:func:`entry_problem`), and, when the file
    exists but cannot be used (unreadable, not JSON, another layout or version), why (one line);
    entries are then empty."""
    shown = cache_shown(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}, None
    except (OSError, ValueError) as err:
        return {}, f"cache {shown} cannot be read ({type(err).__name__}): measured again"
    try:
        doc = json.loads(text)
    except ValueError as err:
        return {}, f"cache {shown} is not JSON ({str(err).splitlines()[0][:80]}): measured again"
    if not isinstance(doc, dict) or not isinstance(doc.get("entries"), dict):
        return {}, f"cache {shown} holds no entries record: measured again"
    if doc.get("version") != CACHE_VERSION:
        version = str(doc.get("version"))[:20]
        return {}, f"cache {shown} is of version {version}, not {CACHE_VERSION}: measured again"
    return doc["entries"], None


def read_cache(path: Path) -> dict[str, Any]:
    """The cache's entries, not yet validated; empty when the file is missing, unreadable or of
    another version."""
    return load_cache(path)[0]


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def entry_problem(entry: Any, field_name: str, names: tuple[str, ...]) -> str | None:
    """None when ``entry`` is a well-formed cache record, else what is wrong (one line). A record
    holds ``field_name`` ("engine" or "head") with one of ``names``, ``ms`` mapping some of ``names``
    to finite times >= 0, and optionally ``ratio`` (finite, > 0, or null), ``reason`` (a string) and
    ``scans`` (an integer >= 0)."""
    if not isinstance(entry, dict):
        return f"a {type(entry).__name__} where a record belongs"
    if entry.get(field_name) not in names:
        return f"{field_name} is {str(entry.get(field_name))[:40]!r}, not one of {', '.join(names)}"
    ms = entry.get("ms", {})
    if not isinstance(ms, dict):
        return f"ms is a {type(ms).__name__}, not a record"
    for name, value in ms.items():
        if name not in names:
            return f"ms names {str(name)[:40]!r}, not one of {', '.join(names)}"
        if not _number(value) or value < 0:
            return f"ms[{name!r}] is {str(value)[:40]!r}, not a time"
    ratio = entry.get("ratio")
    if ratio is not None and (not _number(ratio) or ratio <= 0):
        return f"ratio is {str(ratio)[:40]!r}, not a positive number"
    if not isinstance(entry.get("reason", ""), str):
        return f"reason is a {type(entry['reason']).__name__}, not a string"
    scans = entry.get("scans", 0)
    if not isinstance(scans, int) or isinstance(scans, bool) or scans < 0:
        return f"scans is {str(scans)[:40]!r}, not a count"
    return None


def write_cache(path: Path, new: dict[str, dict[str, Any]]) -> str:
    """Merge ``new`` into the cache file atomically; -> "written" or why not (one line)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        entries = {**read_cache(path), **new}
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".providers-", suffix=".tmp")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump({"version": CACHE_VERSION, "entries": entries}, f, indent=1, sort_keys=True)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as err:
        return f"not written: {type(err).__name__}: {err.strerror or err}"
    return "written"


class Cache:
    """The cache file read once, on first need; entries validated as they are looked up."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.notes: list[str] = []  # why the file or an entry was not used
        self._entries: dict[str, Any] | None = None

    def get(self, key: str, field_name: str, names: tuple[str, ...], what: str) -> dict[str, Any] | None:
        """The entry of ``key`` from this process's picks or the file, None when absent or when
        it does not validate (then with a note naming ``what``)."""
        if key in _MEMO:
            return _MEMO[key]
        if self._entries is None:
            self._entries, note = load_cache(self.path)
            self.notes += [note] if note else []
        if key not in self._entries:
            return None
        why = entry_problem(self._entries[key], field_name, names)
        if why is not None:
            self.notes.append(f"cache entry for {what} does not validate ({why}): measured again")
            return None
        return self._entries[key]

    def keep(self, key: str, entry: dict[str, Any]) -> None:
        """Remember ``entry`` as the pick of ``key`` for the rest of this process."""
        _MEMO[key] = entry
