"""One error type for bad input, and the CLI wrapper that turns it into one line and an exit code.

A runtime-only install (``pip install msdnet``) holds the engine alone; the tools come with extras
(``pyproject.toml``). A command that reaches a package of a missing extra ends, like bad input,
in one line that names the ``pip install`` to run (``missing_extra``).
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

EXIT_BAD_INPUT = 2

# the importable name of a package an extra brings -> the extra that brings it
EXTRA_OF = {
    "matplotlib": "pictures",
    "scipy": "metrics",
    "pypatchworkpp": "metrics",
    "plyfile": "formats",
    "pypcd4": "formats",
    "torch": "train",
    "onnx": "train",
    "safetensors": "train",
    "small_gicp": "bench",
    "cryptography": "sign",
    "rosbags": "ros",
    "ray": "ray",
    "rerun": "rerun",
    "cyclonedds": "live",
    "foxglove": "live",
    "yaml": "live",
    "openvino": "openvino",
}


class MsdnetError(Exception):
    """Bad input: names the file (or other subject) and the cause, in one line.

    ``str(err)`` is ``"<path>: <cause>"``; the CLIs print exactly that, never a traceback.
    """

    def __init__(self, path: str | Path | None, cause: str) -> None:
        self.path = None if path is None else str(path)
        self.cause = cause
        super().__init__(f"{self.path}: {cause}" if self.path else cause)


# extras that also bring packages of others -> the packages a missing-extra line names them for
BUNDLES = {
    "train": {"torch", "onnx", "safetensors", "scipy", "pypatchworkpp"},
    "bench": {"small_gicp", "onnx", "matplotlib", "scipy", "pypatchworkpp", "plyfile", "pypcd4"},
    "ros": {"rosbags", "scipy"},
}
# a command whose jobs come with one of the BUNDLES -> that extra
EXTRA_OF_COMMAND = {"msdnet-train": "train", "msdnet-export": "train", "msdnet-bench": "bench"}


def _running_command() -> tuple[str | None, str | None]:
    """(the running click command's path, the extra of its root command) when one runs."""
    import click

    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return None, None
    return ctx.command_path, EXTRA_OF_COMMAND.get(ctx.find_root().info_name or "")


def missing_extra(
    err: ModuleNotFoundError, what: str | None = None, extra: str | None = None
) -> MsdnetError | None:
    """The one-line error for a package of an extra that is not installed (``what`` needs it;
    ``extra``: the bundle to name where it holds the package, else ``EXTRA_OF``'s); None for any
    other missing module."""
    package = (err.name or "").split(".")[0]
    extra = extra if package in BUNDLES.get(extra or "", ()) else EXTRA_OF.get(package)
    if extra is None:
        return None
    return MsdnetError(
        what,
        f"{'needs' if what else 'this needs'} {package}, which this install leaves out: "
        f"pip install 'msdnet[{extra}]' (in a clone: pip install -e '.[{extra}]')",
    )


def require_extra(package: str, what: str, extra: str | None = None) -> None:
    """MsdnetError naming the extra to install (``extra``, else ``EXTRA_OF``'s) when ``package`` is
    missing, without importing it (for the checks a command makes before any work)."""
    if importlib.util.find_spec(package) is None:
        missing = missing_extra(ModuleNotFoundError(name=package), what, extra)
        raise missing or MsdnetError(what, f"needs {package}")


def import_extra(package: str, what: str) -> Any:
    """``import package``; MsdnetError naming the extra to install when it is missing."""
    try:
        return importlib.import_module(package)
    except ModuleNotFoundError as err:
        missing = missing_extra(err, what)
        if missing is None:
            raise
        raise missing from None


def one_line_errors(func: F) -> F:
    """Decorate a click command: an :class:`MsdnetError`, or a missing extra's package
    (``missing_extra``), becomes ``error: <msg>`` and exit 2."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except MsdnetError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(EXIT_BAD_INPUT)
        except ModuleNotFoundError as err:
            command, extra = _running_command()
            missing = missing_extra(err, command, extra)
            if missing is None:
                raise
            print(f"error: {missing}", file=sys.stderr)
            sys.exit(EXIT_BAD_INPUT)

    return wrapper  # type: ignore[return-value]
