"""Atomic writes and the temporary files they leave: every file msdnet writes goes through here.

``atomic_output(path)`` yields a temporary path next to ``path`` and, on success, moves it over
``path`` with ``os.replace``. Temporary names are ``.msdnet-<pid>-<random>.<name>.tmp`` cut to
255 bytes (``temp_name``); a run killed mid-write leaves one behind, and ``clean_stale_temps``
(called by every CLI before it writes into a folder) removes those whose process is gone. A
failed write is one ``MsdnetError`` naming the output (``write_error``), and says when the disk
is full.

Every command shares two more steps: ``check_writable(path, kind)`` before any work (the place
takes a file, proved by one probe; a killed run's temporaries there are removed; the
``checks_outputs`` decorator runs it on a command's output options), and ``atomic_folder(path)``
for a whole folder (built under a ``temp_name`` next to it, renamed when complete, removed on
failure; a killed run's folder is removed by the next run's check or ``atomic_folder``).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import re
import secrets
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from msdnet.runtime.errors import MsdnetError

TEMP_PREFIX = ".msdnet-"  # every temporary file or folder msdnet writes starts with this
_TEMP_RE = re.compile(r"^\.msdnet-(\d+)-[0-9a-f]+\..*\.tmp$")
MAX_NAME_BYTES = 255  # file name limit of common file systems (ext4, xfs, btrfs, tmpfs)
F = TypeVar("F", bound=Callable[..., Any])


def temp_name(target_name: str, pid: int | None = None) -> str:
    """``.msdnet-<pid>-<random>.<target_name>.tmp``, the target name cut so the whole name fits
    in ``MAX_NAME_BYTES`` bytes of UTF-8 (a legal 255-byte target name still gets a legal temp)."""
    head = f"{TEMP_PREFIX}{os.getpid() if pid is None else pid}-{secrets.token_hex(4)}."
    room = MAX_NAME_BYTES - len(head.encode()) - len(".tmp")
    cut = target_name.encode("utf-8")[:room].decode("utf-8", errors="ignore")
    return f"{head}{cut}.tmp"


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` can still write: it exists and is not a zombie (a killed writer
    whose parent died too stays a zombie until something reaps it; it writes nothing more)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, belongs to someone else
        pass
    try:  # Linux: the state letter after the "(comm)" field
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return True
    return state not in ("Z", "X")


def clean_stale_temps(folder: str | Path) -> int:
    """Remove msdnet temporary files/folders in ``folder`` whose writing process is gone (a
    killed run's leftovers); -> how many were removed. Others' live temps are left alone."""
    removed = 0
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return 0
    for entry in entries:
        match = _TEMP_RE.match(entry.name)
        if not match or _pid_alive(int(match.group(1))):
            continue
        with contextlib.suppress(OSError):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
            removed += 1
    return removed


OUTPUT_KINDS = ("file", "folder", "into")  # what check_writable's ``kind`` may be


def check_writable(path: str | Path, kind: str = "file") -> Path:
    """Before any work: prove ``path`` can be written, or raise one MsdnetError naming it.

    ``kind``: ``"file"``, a file written whole (an existing folder there is refused);
    ``"folder"``, a folder written whole under a temporary name beside it and renamed
    (``atomic_folder``; an existing file there is refused); ``"into"``, a folder that files are
    written into (an existing file there is refused). The folder that receives the new entries
    (``path`` for ``"into"``, else its parent) is probed with one temporary file; folders created
    for the probe are removed with it, so a refused command leaves nothing behind. A killed run's
    temporaries there are removed (``clean_stale_temps``). -> ``path``."""
    if kind not in OUTPUT_KINDS:
        raise ValueError(f"kind must be one of {OUTPUT_KINDS}, got {kind!r}")
    target = Path(path)
    if kind == "file" and target.is_dir():
        raise MsdnetError(target, "is a folder; a file path is needed")
    if kind != "file" and target.exists() and not target.is_dir():
        raise MsdnetError(target, "exists and is not a folder")
    place = target if kind == "into" else target.parent
    missing = [d for d in (place, *place.parents) if not d.exists()]  # deepest first
    probe = place / temp_name("write-check")
    try:
        place.mkdir(parents=True, exist_ok=True)
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        os.unlink(probe)
    except OSError as err:
        raise write_error(target, err) from None
    finally:
        for folder in missing:
            with contextlib.suppress(OSError):
                folder.rmdir()
    clean_stale_temps(place)
    return target


def checks_outputs(**kinds: str) -> Callable[[F], F]:
    """Decorate a command function: before it runs, every keyword argument named in ``kinds``
    that is not None is checked with ``check_writable(value, kind)``, so a command whose output
    cannot be written fails in one line before any work (put it under ``one_line_errors``)."""
    for kind in kinds.values():
        if kind not in OUTPUT_KINDS:
            raise ValueError(f"kind must be one of {OUTPUT_KINDS}, got {kind!r}")

    def decorate(func: F) -> F:
        @functools.wraps(func)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            for name, kind in kinds.items():
                if kwargs.get(name) is not None:
                    check_writable(kwargs[name], kind)
            return func(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return decorate


@contextlib.contextmanager
def atomic_folder(path: str | Path) -> Iterator[Path]:
    """Yield a new temporary folder next to ``path`` (``temp_name``: pid-tagged); on success it
    is renamed to ``path`` (which must not exist then), on any failure removed. A run killed
    meanwhile leaves it behind and the next ``check_writable`` / ``clean_stale_temps`` of that
    parent removes it. An OSError is one MsdnetError naming ``path``."""
    target = Path(path)
    tmp = target.parent / temp_name(target.name)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        clean_stale_temps(target.parent)
        tmp.mkdir()
    except OSError as err:
        raise write_error(target, err) from None
    try:
        yield tmp
        tmp.rename(target)
    except OSError as err:
        raise write_error(target, err) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def write_error(path: str | Path, err: OSError) -> MsdnetError:
    """A failed write as one line naming ``path``; says so when the disk is full (ENOSPC, a
    quota, or numpy's short-write message "N requested and M written")."""
    text = " ".join(str(err).split())
    if err.errno in (errno.ENOSPC, errno.EDQUOT) or re.search(r"\d+ requested and \d+ written", text):
        return MsdnetError(path, "cannot write: no space left on the device (disk full)")
    if err.errno == errno.EROFS:
        return MsdnetError(path, "cannot write: read-only file system")
    return MsdnetError(path, f"cannot write: {err.strerror or text or type(err).__name__}")


@contextlib.contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path`` atomically.

    Any ``OSError`` (disk full, read-only, permissions) becomes one :class:`MsdnetError` naming
    ``path``; the temporary file is removed."""
    target = Path(path)
    tmp = target.parent / temp_name(target.name)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))  # umask applies
    except OSError as err:
        raise write_error(target, err) from None
    try:
        yield tmp
        os.replace(tmp, target)
    except BaseException as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(err, OSError):
            raise write_error(target, err) from None
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
