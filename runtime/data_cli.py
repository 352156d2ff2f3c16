"""``msdnet-data``: simulate paired radar/LiDAR sequences, print statistics, render BEV pictures."""

from __future__ import annotations

import click

from msdnet.runtime.sim.command import simulate
from msdnet.runtime.viz_command import show, stats


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Data tools for msdnet: simulator, dataset statistics and BEV pictures."""


main.add_command(simulate)
main.add_command(show)
main.add_command(stats)
