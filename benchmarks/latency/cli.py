"""``msdnet-bench latency``: the click command around :func:`msdnet.benchmarks.latency.suite.run_latency`."""

from __future__ import annotations

from pathlib import Path

import click

from msdnet.benchmarks.eval_cli import int_tuple
from msdnet.runtime.errors import one_line_errors
from msdnet.runtime.io.atomic import checks_outputs
from msdnet.runtime.io.datasets import DATASET_NAMES


@click.command("latency", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Folder for results.*")
@click.option(
    "--preset", type=click.Choice(["tiny", "lite", "paper", "paper-width"]), help="Random models [lite]."
)
@click.option("--model", type=click.Path(path_type=Path), help="Exported MSDNet folder.")
@click.option(
    "--head",
    type=click.Choice(["dense", "gated", "sparse"]),
    help="Recon head of random models [dense].",
)
@click.option("--loop-steps", type=click.IntRange(min=1), help="DDIM steps T_m of random models [preset].")
@click.option(
    "--up-sampling",
    type=click.Choice(["conv_transpose", "depth_to_space"]),
    help="Head up-sampling of random models' graphs; depth_to_space: the older export form.",
)
@click.option("--r2ldm", type=click.Path(path_type=Path), help="Exported R2LDM folder [random].")
@click.option(
    "--provider",
    default="auto",
    show_default=True,
    help="auto (as msdnet-infer), cpu, cpu-shared, auto-bf16, openvino, openvino-bf16, cuda or tensorrt.",
)
@click.option("--threads", type=click.IntRange(min=1), help="Intra-op threads [all cores].")
@click.option("--repeats", type=click.IntRange(min=1), help="Timed MSDNet frames [30; quick 3].")
@click.option("--warmup", type=click.IntRange(min=0), help="Untimed frames first [3; quick 1].")
@click.option("--r2ldm-repeats", type=click.IntRange(min=1), help="Timed R2LDM frames [5; quick 1].")
@click.option(
    "--steps", "steps_text", help="Steps sweep, e.g. 1,3,10,25,50,100 (time, and quality with --data)."
)
@click.option("--points", "points_text", help="Input-size sweep, e.g. 1000,10000,100000.")
@click.option(
    "--target-points",
    type=click.IntRange(min=1),
    default=20000,
    show_default=True,
    help="Random weights: threshold leaving about this many decoded points.",
)
@click.option("--int8/--no-int8", default=True, show_default=True, help="Measure an INT8 step graph.")
@click.option(
    "--peers/--no-peers", default=True, show_default=True, help="Time OpenVINO and torch per stage."
)
@click.option(
    "--torch-compile/--no-torch-compile",
    default=None,
    help="torch.compile among the peers (compiles for minutes) [on; quick off].",
)
@click.option(
    "--peer-repeats", type=click.IntRange(min=1), help="Interleaved repeats of the peer table [5; quick 2]."
)
@click.option(
    "--peers-on-one-frame",
    is_flag=True,
    help="Time the peers on the timing input repeated, not on a stream of "
    "distinct frames; OpenVINO looks faster so.",
)
@click.option(
    "--stream-frames",
    type=click.IntRange(min=0),
    help="Whole frames on a stream: this many distinct frames, each once (other --data frames than "
    "the rest of the run reads, else seeded scans; 0: skip) [30; quick 3].",
)
@click.option(
    "--against-old",
    is_flag=True,
    help="Random models: also time the same model with its unoptimised graphs (dense head, "
    "old up-sampling, T_m 50, cpu), interleaved in this run.",
)
@click.option(
    "--before",
    type=click.Path(path_type=Path),
    help="A previous MSDNet folder (e.g. a copy of the shipped model): time it against the new "
    "pipeline, both fresh at --provider, interleaved on the same stream of scans; ratios "
    "frame_over_before and encoder_over_before.",
)
@click.option(
    "--data", type=click.Path(path_type=Path), help="Dataset root: quality against T_m on its frames."
)
@click.option("--dataset", type=click.Choice(DATASET_NAMES), help="Layout of --data.")
@click.option("--frames", type=click.IntRange(min=1), help="Frames scored per T_m [10; quick 1].")
@click.option("--seed", type=int, default=0, show_default=True, help="Weights, inputs and noise.")
@click.option("--quick", is_flag=True, help="Tiny preset, few repetitions, short sweeps (seconds).")
@one_line_errors
@checks_outputs(out="into")  # before any work
def latency_command(
    out: Path,
    preset: str | None,
    model: Path | None,
    head: str | None,
    loop_steps: int | None,
    up_sampling: str | None,
    r2ldm: Path | None,
    provider: str,
    threads: int | None,
    repeats: int | None,
    warmup: int | None,
    r2ldm_repeats: int | None,
    steps_text: str | None,
    points_text: str | None,
    target_points: int,
    int8: bool,
    peers: bool,
    torch_compile: bool | None,
    peer_repeats: int | None,
    peers_on_one_frame: bool,
    stream_frames: int | None,
    against_old: bool,
    before: Path | None,
    data: Path | None,
    dataset: str | None,
    frames: int | None,
    seed: int,
    quick: bool,
) -> None:
    """Time per stage and per frame, against peer engines, T_m and input size; writes
    results.json, results.md and plots."""
    from msdnet.benchmarks.latency.suite import LatencyConfig, quick_config, run_latency
    from msdnet.runtime.providers.session import resolve_providers

    resolve_providers(provider)
    given = {
        "preset": preset,
        "model": model,
        "head": head,
        "loop_steps": loop_steps,
        "up_sampling": up_sampling,
        "r2ldm": r2ldm,
        "provider": provider,
        "threads": threads,
        "repeats": repeats,
        "warmup": warmup,
        "r2ldm_repeats": r2ldm_repeats,
        "steps": int_tuple("--steps", steps_text, 1),
        "point_counts": int_tuple("--points", points_text, 1),
        "target_points": target_points,
        "int8": int8,
        "peers": peers,
        "torch_compile": torch_compile,
        "peer_repeats": peer_repeats,
        "peer_stream": not peers_on_one_frame,
        "stream_frames": stream_frames,
        "against_old": against_old,
        "before": before,
        "data": data,
        "dataset": dataset,
        "frames": frames,
        "seed": seed,
    }
    kw = {k: v for k, v in given.items() if v is not None}
    if quick and model is not None:
        kw.setdefault("preset", None)  # the model fixes its own preset
    cfg = quick_config(out, **kw) if quick else LatencyConfig(out=out, **kw)
    res = run_latency(cfg, log=lambda s: click.echo(s, err=True))
    for g in res["goals"]:
        met = {True: "met", False: "NOT met", None: "n/a"}[g["met"]]
        value = g["measured"]
        shown = f"{value:.3g}" if isinstance(value, float) else str(value)
        click.echo(f"{g['goal']:<48} {shown:>10}  (target {g['target']}: {met})")
    click.echo(f"wrote {out / 'results.json'}, {out / 'results.md'} and plots")
