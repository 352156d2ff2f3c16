"""``msdnet-bench``: voxelize, quality, odometry, place, latency, encoders, params, steps, stages,
conditioning, soak, live, node-exit, fuzz."""

from __future__ import annotations

import click

from msdnet.benchmarks.conditioning import conditioning_command
from msdnet.benchmarks.eval_cli import odometry_command, place_command, quality_command
from msdnet.benchmarks.fuzz import fuzz_command
from msdnet.benchmarks.latency.cli import latency_command
from msdnet.benchmarks.latency.encoder_forms import encoders_command
from msdnet.benchmarks.latency.steps import steps_command
from msdnet.benchmarks.live import live_command
from msdnet.benchmarks.node_exit import node_exit_command
from msdnet.benchmarks.params import params_command
from msdnet.benchmarks.soak import soak_command
from msdnet.benchmarks.stages import stages_command
from msdnet.benchmarks.training_speed import training_speed_command
from msdnet.benchmarks.voxelize_bench import voxelize_command


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Benchmarks for msdnet: speed and quality against references and the papers."""


main.add_command(voxelize_command)
main.add_command(quality_command)
main.add_command(odometry_command)
main.add_command(place_command)
main.add_command(latency_command)
main.add_command(encoders_command)  # the encoder in its two forms (benchmarks/latency/encoder_forms.py)
main.add_command(params_command)  # the papers' size table beside the latency one (benchmarks/params.py)
main.add_command(steps_command)  # Table III: the T_m sweep on a dataset split (benchmarks/latency/steps.py)
main.add_command(stages_command)
main.add_command(conditioning_command)
main.add_command(soak_command)  # resident memory of one msdnet-infer process (benchmarks/soak.py)
main.add_command(live_command)  # msdnet-node end to end on loopback (benchmarks/live.py)
main.add_command(node_exit_command)  # msdnet-node stopped by a signal on first runs (benchmarks/node_exit.py)
main.add_command(fuzz_command)  # mutated inputs through every reader (benchmarks/fuzz.py)
main.add_command(training_speed_command)  # step time before / after (benchmarks/training_speed.py)
