"""Click pieces the ``msdnet-*`` commands share: a group whose sub-commands load when they run.

``LazyGroup`` lists its sub-commands from their names and one-line help alone, and imports a
sub-command only when it runs or its own ``--help`` is asked. So a group's ``--help`` works in a
runtime-only install, and a sub-command whose code needs a missing extra (torch, scipy, ...)
ends in one line naming the ``pip install`` to run, exit 2, never a traceback. With ``default``,
a first argument that names no sub-command runs the default one with all the arguments
(``msdnet-export CHECKPOINT --out DIR``).
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass
from typing import Any

import click

from msdnet.runtime.errors import EXIT_BAD_INPUT, EXTRA_OF_COMMAND, missing_extra


@dataclass(frozen=True)
class Lazy:
    """A sub-command by where it lives: ``target`` is ``"module:attr"``, a click command or a
    function of the sub-command's name that makes one; ``help`` is its line in the group's help."""

    target: str
    help: str


class LazyGroup(click.Group):
    """A click group of ``Lazy`` sub-commands (see the module docstring)."""

    def __init__(
        self, *args: Any, lazy: dict[str, Lazy] | None = None, default: str | None = None, **kw: Any
    ):
        super().__init__(*args, **kw)
        self.lazy = dict(lazy or {})
        self.default = default

    def list_commands(self, ctx: click.Context) -> list[str]:
        """The sub-commands in the order they were given (the lazy ones first)."""
        return [*self.lazy, *(name for name in self.commands if name not in self.lazy)]

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name in self.commands or cmd_name not in self.lazy:
            return super().get_command(ctx, cmd_name)
        module, attr = self.lazy[cmd_name].target.split(":")
        try:
            found = getattr(importlib.import_module(module), attr)
            command = found if isinstance(found, click.Command) else found(cmd_name)
        except ModuleNotFoundError as err:
            extra = EXTRA_OF_COMMAND.get(ctx.find_root().info_name or "")
            missing = missing_extra(err, f"{ctx.command_path} {cmd_name}", extra)
            if missing is None:
                raise
            click.echo(f"error: {missing}", err=True)
            sys.exit(EXIT_BAD_INPUT)
        self.commands[cmd_name] = command
        return command

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        known = set(self.list_commands(ctx))
        if self.default and args and not args[0].startswith("-") and args[0] not in known:
            args = [self.default, *args]
        return super().parse_args(ctx, args)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The sub-commands and their lines, without importing the lazy ones."""
        limit = formatter.width - 6 - max((len(n) for n in self.list_commands(ctx)), default=0)
        rows: list[tuple[str, str]] = []
        for name in self.list_commands(ctx):
            if name in self.lazy and name not in self.commands:
                rows.append((name, self.lazy[name].help))
                continue
            command = self.commands[name]
            if not command.hidden:
                rows.append((name, command.get_short_help_str(limit)))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


def lazy_group(name: str, help_text: str, lazy: dict[str, Lazy], default: str | None = None) -> LazyGroup:
    """A ``LazyGroup`` named ``name`` that does nothing itself; ``-h`` works like ``--help``."""
    return LazyGroup(
        name=name,
        help=help_text,
        lazy=lazy,
        default=default,
        context_settings={"help_option_names": ["-h", "--help"]},
    )
