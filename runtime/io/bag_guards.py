"""Guards around a ROS 2 bag ``msdnet-infer --topic`` reads and writes (``runtime/io/rosbag``).

- ``storage_of``: the storage plugin a bag's ``metadata.yaml`` names; a broken file, or one written
  by another tool (no ``rosbag2_bagfile_information.storage_identifier``), is one line naming the bag.
- ``prepare_bag_out``: before any work, the output bag's folder must take a file (a read-only
  place is one line naming the output), and a killed run's temporary bag there is removed
  (``io.atomic.clean_stale_temps``: pid-tagged temp names whose process is gone).
- ``bag_write_error``: a failed write (OSError, sqlite3 or rosbags error) as one line naming the
  output: disk full, read-only, or the library's cause.
"""

from __future__ import annotations

from pathlib import Path

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.io.atomic import check_writable, write_error


def storage_of(bag: Path) -> str:
    """The storage plugin ``metadata.yaml`` names; MsdnetError naming the bag when it is broken,
    unreadable or not a rosbag2 one."""
    from ruamel.yaml import YAML  # a rosbags dependency

    try:
        meta = YAML(typ="safe").load((bag / "metadata.yaml").read_text(encoding="utf-8"))
        info = meta["rosbag2_bagfile_information"]
        storage = info["storage_identifier"]
    except (KeyError, TypeError):
        raise MsdnetError(bag, "metadata.yaml is not a rosbag2 one (no storage_identifier)") from None
    except Exception as err:  # YAML syntax, bad bytes, permissions
        cause = " ".join(str(err).split())[:160] or type(err).__name__
        raise MsdnetError(bag, f"metadata.yaml is unreadable: {cause}") from None
    if not isinstance(storage, str):
        raise MsdnetError(bag, f"metadata.yaml names storage {storage!r}, not a plugin name")
    return storage


def prepare_bag_out(out: Path) -> None:
    """Before any work: ``out``'s folder exists and takes a file (one probe, removed); a killed
    run's temporary bags there are removed."""
    check_writable(out, "folder")  # a ROS 2 bag is a folder, written beside and renamed
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise write_error(out, err) from None


def bag_write_error(out: Path, err: Exception) -> MsdnetError:
    """A failed bag write (OSError, sqlite3 or rosbags error) as one line naming ``out``."""
    if isinstance(err, OSError):
        return write_error(out, err)
    text = " ".join(str(err).split())[:200] or type(err).__name__
    if "disk is full" in text or "No space left" in text:
        return MsdnetError(out, "cannot write: no space left on the device (disk full)")
    if "readonly" in text or "read-only" in text:
        return MsdnetError(out, "cannot write: read-only file system")
    return MsdnetError(out, f"cannot write the bag: {text}")
