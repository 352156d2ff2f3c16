"""One error type for bad input, and the CLI wrapper that turns it into one line and an exit code."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

EXIT_BAD_INPUT = 2


class MsdnetError(Exception):
    """Bad input: names the file (or other subject) and the cause, in one line.

    ``str(err)`` is ``"<path>: <cause>"``; the CLIs print exactly that, never a traceback.
    """

    def __init__(self, path: str | Path | None, cause: str) -> None:
        self.path = None if path is None else str(path)
        self.cause = cause
        super().__init__(f"{self.path}: {cause}" if self.path else cause)


def one_line_errors(func: F) -> F:
    """Decorate a click command: an :class:`MsdnetError` becomes ``error: <msg>`` and exit 2."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except MsdnetError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(EXIT_BAD_INPUT)

    return wrapper  # type: ignore[return-value]
