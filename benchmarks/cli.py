"""``msdnet-bench``: the benchmark commands (voxelize; quality, latency, ... join later)."""

from __future__ import annotations

import click

from msdnet.benchmarks.voxelize_bench import voxelize_command


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Benchmarks for msdnet: speed and quality against references and the papers."""


main.add_command(voxelize_command)
