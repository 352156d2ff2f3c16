"""``msdnet-data``: simulate paired radar/LiDAR sequences, print statistics, render BEV pictures,
pair a bag's radar and LiDAR into a training folder."""

from __future__ import annotations

import click

from msdnet.runtime.frontends.data.pair import pair
from msdnet.runtime.frontends.data.show_stats import show, stats
from msdnet.runtime.sim.command import simulate


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Data tools for msdnet: simulator, dataset statistics and BEV pictures."""


main.add_command(simulate)
main.add_command(show)
main.add_command(stats)
main.add_command(pair)  # bag -> VoD-layout training folder (runtime/io/pairing)
