"""Atomic writes and the temporary files they leave: every file msdnet writes goes through here.

``atomic_output(path)`` yields a temporary path next to ``path`` and, on success, moves it over
``path`` with ``os.replace``. Temporary names are ``.msdnet-<pid>-<random>.<name>.tmp`` cut to
255 bytes (``temp_name``); a run killed mid-write leaves one behind, and ``clean_stale_temps``
(called by every CLI before it writes into a folder) removes those whose process is gone. A
failed write is one ``MsdnetError`` naming the output (``write_error``), and says when the disk
is full.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import shutil
from collections.abc import Iterator
from pathlib import Path

from msdnet.runtime.errors import MsdnetError

TEMP_PREFIX = ".msdnet-"  # every temporary file or folder msdnet writes starts with this
_TEMP_RE = re.compile(r"^\.msdnet-(\d+)-[0-9a-f]+\..*\.tmp$")
MAX_NAME_BYTES = 255  # file name limit of common file systems (ext4, xfs, btrfs, tmpfs)


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
