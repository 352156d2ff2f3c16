"""``msdnet-bench soak``: resident memory of one ``msdnet-infer`` process over thousands of frames.

A folder of ``frames`` links to the INPUTS files (in turn, so consecutive frames differ) goes
through ONE ``msdnet-infer`` process, exactly as a user runs it (read, voxelize, encoder, DDIM
loop, head, decode, atomic write, per file; the summary rows accumulate). This process polls
the child's resident set size (``VmRSS`` in ``/proc/<pid>/status``) and the number of outputs
written every ``poll`` seconds. The baseline is the RSS when ``warmup`` (100) outputs exist;
the growth is (RSS at the first poll that finds every output written - baseline) / baseline
(before the process's teardown frees memory), and the peak growth is the same with the largest
RSS seen after the baseline. The run passes when the growth is below ``limit_pct`` (5 %).
Linux only (``/proc``). Results: ``OUT/soak.json`` and ``OUT/soak.md``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import click
from tqdm import tqdm

from msdnet.benchmarks.machine import machine_info
from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.frontends.infer.files import collect_inputs
from msdnet.runtime.frontends.model_args import resolve_model
from msdnet.runtime.io.atomic import atomic_output, checks_outputs


@dataclass(frozen=True)
class SoakResult:
    """One soak run; memory in MiB of resident set size of the msdnet-infer process."""

    model: str  # model folder
    inputs: int  # distinct input files, used in turn
    frames: int  # frames run through the one process
    warmup: int  # frames done when the baseline was taken
    steps: int | None  # --steps (None: the manifest's T_m)
    threads: int | None  # --threads
    rss_baseline_mib: float  # RSS when `warmup` outputs existed
    rss_final_mib: float  # RSS when every output was written (before the process's teardown)
    rss_peak_mib: float  # largest RSS seen after the baseline
    growth_pct: float  # (final - baseline) / baseline * 100
    peak_growth_pct: float  # (peak - baseline) / baseline * 100
    limit_pct: float  # pass when growth_pct < limit_pct
    passed: bool
    seconds: float  # wall time of the msdnet-infer process
    exit_code: int  # msdnet-infer's exit code
    samples: list[tuple[int, float]]  # (outputs written, RSS MiB), one per 100 frames


def rss_mib(pid: int) -> float | None:
    """Resident set size of ``pid`` in MiB, None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _count(folder: Path, suffix: str) -> int:
    with os.scandir(folder) as it:
        return sum(1 for e in it if e.name.endswith(suffix))


def run_soak(
    inputs: list[Path],
    model: Path,
    frames: int,
    warmup: int,
    steps: int | None,
    threads: int | None,
    limit_pct: float,
    poll: float = 0.1,
) -> SoakResult:
    """Run ``frames`` frames through one msdnet-infer process and measure its RSS."""
    if warmup >= frames:
        raise MsdnetError("--warmup", f"must be below --frames ({frames}), got {warmup}")
    exe = Path(sys.executable).with_name("msdnet-infer")
    with tempfile.TemporaryDirectory(prefix="msdnet-soak-") as tmp:
        src, out = Path(tmp) / "radar", Path(tmp) / "out"  # "radar": .bin layout by folder name
        src.mkdir()
        for i in range(frames):
            f = inputs[i % len(inputs)]
            os.symlink(f.resolve(), src / f"f{i:06d}{f.suffix.lower()}")
        cmd = [str(exe), str(src), "--model", str(model), "--out", str(out)]
        cmd += [] if steps is None else ["--steps", str(steps)]
        cmd += [] if threads is None else ["--threads", str(threads)]
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        baseline = final = peak = None
        locked = False
        samples: list[tuple[int, float]] = []
        bar = tqdm(total=frames, unit="frame", desc="soak", disable=None)
        while proc.poll() is None:
            time.sleep(poll)
            done = _count(out, ".npy") if out.is_dir() else 0
            rss = rss_mib(proc.pid)
            if rss is None:
                continue
            bar.update(done - bar.n)
            if baseline is None and done >= warmup:
                baseline = peak = rss
            if baseline is not None and not locked:  # stop at the last frame, before teardown
                peak, final, locked = max(peak, rss), rss, done >= frames
            if not samples or done // 100 > samples[-1][0] // 100:
                samples.append((done, round(rss, 1)))
        bar.close()
        stdout, stderr = proc.communicate()
        seconds = time.perf_counter() - start
    if proc.returncode != 0 or baseline is None or final is None:
        tail = (stderr.strip().splitlines() or stdout.strip().splitlines() or ["no output"])[-1]
        raise MsdnetError("msdnet-infer", f"soak run failed (exit {proc.returncode}): {tail}")
    growth = 100.0 * (final - baseline) / baseline
    return SoakResult(
        str(model), len(inputs), frames, warmup, steps, threads, round(baseline, 1), round(final, 1),
        round(peak, 1), round(growth, 2), round(100.0 * (peak - baseline) / baseline, 2), limit_pct,
        growth < limit_pct, round(seconds, 1), proc.returncode, samples,
    )  # fmt: skip


def write_results(res: SoakResult, out: Path) -> None:
    """``out/soak.json`` (result + machine) and ``out/soak.md`` (one table)."""
    machine = machine_info(sgemm=False).to_json()
    with atomic_output(out / "soak.json") as tmp:
        tmp.write_text(json.dumps({"result": asdict(res), "machine": machine}, indent=1) + "\n")
    lines = [
        "# msdnet-infer soak",
        "",
        f"{res.frames} frames ({res.inputs} distinct files, in turn) through one msdnet-infer process; "
        f"model `{Path(res.model).name}`, steps {res.steps or 'manifest'}, "
        f"threads {res.threads or 'default'}; "
        f"{res.seconds:.0f} s. Machine: {machine.get('cpu', '?')}.",
        "",
        "| RSS after frame "
        + str(res.warmup)
        + " (MiB) | final (MiB) | peak (MiB) | growth | peak growth | limit |",
        "|---:|---:|---:|---:|---:|---:|",
        f"| {res.rss_baseline_mib:.1f} | {res.rss_final_mib:.1f} | {res.rss_peak_mib:.1f} | "
        f"{res.growth_pct:+.2f} % | {res.peak_growth_pct:+.2f} % | < {res.limit_pct:g} % "
        f"({'pass' if res.passed else 'FAIL'}) |",
        "",
        "RSS every 100 frames (frames written: MiB): " + ", ".join(f"{n}: {m:.0f}" for n, m in res.samples),
        "",
    ]
    with atomic_output(out / "soak.md") as tmp:
        tmp.write_text("\n".join(lines))


@click.command("soak", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("inputs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--model", type=click.Path(path_type=Path), help="msdnet-export folder [bundled].")
@click.option("--frames", type=click.IntRange(min=2), default=2000, show_default=True)
@click.option("--warmup", type=click.IntRange(min=1), default=100, show_default=True, help="Baseline frame.")
@click.option("--steps", type=click.IntRange(min=1), help="DDIM steps [manifest T_m].")
@click.option("--threads", type=click.IntRange(min=1), help="msdnet-infer --threads.")
@click.option("--limit", "limit_pct", type=float, default=5.0, show_default=True, help="Max growth, %.")
@click.option("--out", type=click.Path(path_type=Path), help="Write soak.json and soak.md here.")
@one_line_errors
@checks_outputs(out="into")  # before any work
def soak_command(
    inputs: tuple[Path, ...],
    model: Path | None,
    frames: int,
    warmup: int,
    steps: int | None,
    threads: int | None,
    limit_pct: float,
    out: Path | None,
) -> None:
    """Resident memory of one msdnet-infer process over FRAMES frames taken in turn from INPUTS."""
    if not Path("/proc/self/status").is_file():
        raise MsdnetError("soak", "needs Linux /proc to read the process's resident memory")
    files = collect_inputs(inputs)
    if model is not None:
        from msdnet.benchmarks.args import check_model_folder

        check_model_folder("--model", model)  # before the soak process starts
    res = run_soak(files, resolve_model(model), frames, warmup, steps, threads, limit_pct)
    click.echo(
        f"soak: {res.frames} frames in {res.seconds:.0f} s; RSS {res.rss_baseline_mib:.1f} MiB after "
        f"frame {res.warmup} -> {res.rss_final_mib:.1f} MiB at the end ({res.growth_pct:+.2f} %, "
        f"peak {res.peak_growth_pct:+.2f} %; limit {res.limit_pct:g} %): {'pass' if res.passed else 'FAIL'}"
    )
    if out is not None:
        write_results(res, out)
        click.echo(f"wrote {out / 'soak.json'} and {out / 'soak.md'}")
    if not res.passed:
        raise SystemExit(1)
