"""``msdnet-train``: every training job as a sub-command, loaded when it runs.

- ``teacher``, ``student``, ``r2ldm``: train one network (``cli``, the same options for each);
- ``gated-head``: give a trained student the gated coarse-to-fine head (``recipe.gated_head``).

The group lists them without importing torch, so ``msdnet-train --help`` works in a runtime-only
install and a job there ends in one line naming the ``train`` extra.
"""

from __future__ import annotations

import functools

import click

from msdnet.runtime.frontends.commands import Lazy, lazy_group

KINDS = {
    "teacher": "Train the LiDAR teacher (encoder and reconstruction head).",
    "student": "Train the MSDNet student on a trained teacher's features (--teacher).",
    "r2ldm": "Train the R2LDM baseline on a trained teacher's features (--teacher).",
}


def kind_command(kind: str) -> click.Command:
    """``msdnet-train KIND ...``: the training command with its KIND given."""
    from msdnet.training import cli

    base = cli.main
    return click.Command(
        kind,
        params=[p for p in base.params if p.name != "kind"],
        callback=functools.partial(base.callback, kind),
        help=KINDS[kind],
        context_settings=base.context_settings,
    )


main = lazy_group(
    "msdnet-train",
    "Train MSDNet (a LiDAR teacher, then the student) or the R2LDM baseline, in torch.",
    {
        **{kind: Lazy("msdnet.training.main:kind_command", text) for kind, text in KINDS.items()},
        "gated-head": Lazy(
            "msdnet.training.recipe.gated_head:main",
            "Give a trained student the gated coarse-to-fine head, calibrated on its training frames.",
        ),
    },
)
