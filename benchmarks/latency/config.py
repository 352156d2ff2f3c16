"""Settings of one ``msdnet-bench latency`` run (``suite.run_latency``), the quick run's, and the
checks of its inputs before anything is timed."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class LatencyConfig:
    """Settings of one ``msdnet-bench latency`` run."""

    out: Path  # folder for results.json, results.md and the plots
    preset: str | None = None  # model preset for random models (default lite; --model: its own)
    model: Path | None = None  # exported MSDNet folder; None: random MSDNet + R2LDM of the preset
    head: str | None = None  # random models: "dense", "gated" or "sparse" recon head [dense]
    loop_steps: int | None = None  # random models: the DDIM steps T_m they run [the preset's]
    up_sampling: str | None = None  # random models: head export form (training.nn.head.Up2x) [the exporter's]
    r2ldm: Path | None = None  # exported R2LDM folder; None: random R2LDM on the same config
    provider: str = "cpu"  # short name (runtime.providers.session: cpu, auto, openvino, cuda, tensorrt)
    threads: int = os.cpu_count() or 1  # onnxruntime intra-op threads = torch threads
    repeats: int = 30  # timed MSDNet calls (sweeps use max(2, repeats // 5))
    warmup: int = 3  # untimed calls before timing
    r2ldm_repeats: int = 5  # timed R2LDM calls (128 steps each: slow)
    steps: tuple[int, ...] = (1, 3, 10, 25, 50, 100)  # steps sweep (Table III steps added)
    point_counts: tuple[int, ...] = (1000, 3000, 10000, 30000, 100000)  # input-size sweep
    target_points: int = 20000  # random weights: threshold leaving about this many points
    int8: bool = True  # measure an INT8 step graph
    data: Path | None = None  # dataset root for Table III quality and a real timing input
    dataset: str | None = None  # layout of data: vod, astyx or sim
    frames: int = 10  # frames scored per step count
    seed: int = 0  # weights, inputs and noise
    peers: bool = True  # time the peer engines (OpenVINO, torch eager, torch.compile) per stage
    torch_compile: bool = True  # include torch.compile among the peers (compiles for minutes)
    peer_repeats: int = 5  # interleaved repeats per engine and stage
    peer_stream: bool = True  # peers on a stream of distinct frames; False: one frame repeated (before 12-05)
    stream_frames: int = 30  # whole frames on a stream: this many distinct frames, each once (0: not run)
    against_old: bool = False  # random models: time the old graphs in this run (latency/old_graphs.py)
    before: Path | None = None  # a previous model folder, timed against the new pipeline (latency/before.py)

    @property
    def sweep_repeats(self) -> int:
        return max(2, self.repeats // 5)


def quick_config(out: Path, **kw: Any) -> LatencyConfig:
    """A run of a few seconds on the tiny preset (tests): few repetitions, short sweeps."""
    base: dict[str, Any] = {"preset": "tiny", "repeats": 3, "warmup": 1, "r2ldm_repeats": 1}
    base |= {"steps": (1, 50), "point_counts": (1000, 100000), "frames": 1}
    base |= {"torch_compile": False, "peer_repeats": 2, "stream_frames": 3}
    return LatencyConfig(out=out, **(base | kw))


def check_inputs(cfg: LatencyConfig) -> None:
    """Every model folder and the dataset root, before anything is timed (``benchmarks.args``):
    --model an MSDNet folder, --r2ldm an R2LDM one, --before an MSDNet one, --data a folder."""
    from msdnet.benchmarks.args import check_folder, check_model_folder

    for flag, folder, kinds in (("--model", cfg.model, ("student",)), ("--r2ldm", cfg.r2ldm, ("r2ldm",))):
        if folder is not None:
            check_model_folder(flag, Path(folder), kinds)
    if cfg.before is not None:
        check_model_folder("--before", Path(cfg.before), ("student",))
    if cfg.data is not None:
        check_folder("--data", Path(cfg.data))
