"""``msdnet-bench latency``: where the time of one frame goes, and the papers' Tables III and IV.

One run measures, on one machine and one input (a seeded radar-like scan of 300 points, or the
first frame of ``--data``), after warm-up calls:

- MSDNet per stage (voxelize + rulebooks, encoder, RGFD + adapter, DDIM loop, head, decode, total),
  medians and p90; the same for the R2LDM baseline on the same grid (Table IV with parameters);
- MSDNet per stage on a stream (``--stream-frames`` distinct frames, each once: other ``--data``
  frames than any other measurement reads, else seeded scans), as a sensor feeds it;
- the bare step graph (IOBinding, nothing else), interleaved with the pipeline calls so both see
  the same load: the DDIM loop's share spent outside the step graph, and the step graph's FLOP
  rate against the measured numpy sgemm rate;
- per graph stage, the useful-FLOP efficiency: the FLOPs on occupied voxels only over (median
  time x sgemm rate) (``latency/useful``);
- onnxruntime against torch eager (same weights and inputs, same thread count, inference_mode);
- numba against numpy voxelization; latency against T_m (Table III, with quality when a trained
  model and data are given) and against input points (1k to 100k); the peak RSS of an
  ``msdnet-infer`` process; an INT8 (static QDQ) step graph's speed and quality cost.

Ratios are taken inside this one run, so they hold on a loaded machine better than absolute times;
``os.getloadavg()`` is recorded at the start and the end.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from msdnet.benchmarks.latency.before import before_comparison, before_threshold, load_before
from msdnet.benchmarks.latency.compare import int8_comparison, torch_comparison
from msdnet.benchmarks.latency.config import LatencyConfig, check_inputs, quick_config  # noqa: F401 - cli and tests
from msdnet.benchmarks.latency.head import choose_gate, coarse_to_fine_gate, head_comparison
from msdnet.benchmarks.latency.inputs import (  # tests read _frame_stream, _models and _named here
    STREAM_SEED_STRIDE,
    _frame_stream,
    _inputs,
    _models,
    _named,
    _seeded_scans,
    _stream,
    _target,
    _threshold,
)
from msdnet.benchmarks.latency.models import KINDS, ModelPair
from msdnet.benchmarks.latency.old_graphs import old_comparison
from msdnet.benchmarks.latency.peers import peer_comparison
from msdnet.benchmarks.latency.report import write_outputs
from msdnet.benchmarks.latency.runs import msdnet_timings, stream_timings, sweep
from msdnet.benchmarks.latency.timing import (
    BareStep,
    StageRuns,
    peak_rss_mb,
    summary,
    synthetic_radar,
    time_stages,
    voxelize_figures,
)
from msdnet.benchmarks.latency.useful import efficiency, stage_flops
from msdnet.benchmarks.machine import machine_info
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.providers.session import SHARED

TABLE3_STEPS = (3, 10, 50, 100)  # MSDNet Table III
GRAPH_STAGES = ("encoder", "rgfd_adapter", "ddim_loop", "recon_head")  # what torch eager also runs


def _notes(res: dict[str, Any]) -> list[str]:
    """Remarks a reader needs to judge the figures."""
    notes = []
    t = res["torch_eager"]
    if "torch_1_thread" in t and t["torch_1_thread"]["median"] < t["torch"]["median"]:
        notes.append(
            f"torch eager ran faster at 1 thread than at {t['threads']}: its OpenMP pool spins and "
            "loses its time slices on a loaded machine (onnxruntime runs with spinning off); "
            "onnx_over_best_torch compares against the faster setting."
        )
    m = res["machine"]
    load = max(m["loadavg_start"][0], m["loadavg_end"][0])
    if load > m["logical_cores"]:
        notes.append(
            f"load average up to {load:.1f} on {m['logical_cores']} cores: other work shared the CPU, "
            "so absolute times are upper bounds (the min columns are the least disturbed runs)."
        )
    if res["table3"]["quality"] and res["models"]["msdnet"]["weights"] == "random":
        notes.append("Table III quality was computed with random weights: it says nothing of MSDNet.")
    return notes


def _before(
    cfg: LatencyConfig,
    pair: ModelPair,
    msd: Pipeline,
    points: Any,
    thr: float,
    sensor: list,
    sensor_source: str,
    log: Callable[[str], None],
) -> dict[str, Any]:
    """The new pipeline against ``cfg.before`` (``latency/before``): both loaded fresh at the run's
    provider, on the whole-frame stream's scans (else seeded scans of the timing input's size)."""
    assert cfg.before is not None
    scans, source = sensor, sensor_source
    if not scans:
        scans = _seeded_scans(cfg, msd, points, max(3, cfg.sweep_repeats), STREAM_SEED_STRIDE)
        source = f"{len(scans)} seeded synthetic scans of {len(scans[0])} points"
    log(f"the previous pipeline ({cfg.before}) against the new one, interleaved on {len(scans)} scans ...")
    new = Pipeline.from_dir(pair.msdnet.folder, cfg.provider, cfg.threads)
    new.warmup()
    if pair.msdnet.weights == "random":
        new.gate = msd.gate  # the run's gate; a given model runs as msdnet-infer runs it
    prev = load_before(Path(cfg.before), cfg.provider, cfg.threads)
    if pair.msdnet.weights != "random":  # each decodes as its manifest says (range thresholds, keep rule)
        return before_comparison(new, prev, points, scans, (None, None), source, cfg.seed)
    prev_thr = before_threshold(prev, pair.msdnet.weights, points, msd, _target(msd, cfg), cfg.seed)
    return before_comparison(new, prev, points, scans, (thr, prev_thr), source, cfg.seed)


def run_latency(cfg: LatencyConfig, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run every measurement of the module docstring, write the outputs; -> results.json's dict."""
    if (cfg.data is None) != (cfg.dataset is None):
        raise MsdnetError("--data", "--data and --dataset go together")
    if cfg.provider.strip().lower() == SHARED and (cfg.peers or cfg.against_old or cfg.before):
        raise MsdnetError(
            "--provider",
            f"{SHARED}'s pool spins between graphs and would slow the engines timed beside it: "
            "use --no-peers, without --against-old or --before",
        )
    check_inputs(cfg)  # the model folders and the data root, before anything is timed
    load_start = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="msdnet-latency-") as tmp:
        scratch = Path(tmp)
        pair = _models(cfg, scratch)
        log("measuring the machine (sgemm) ...")
        machine = machine_info().to_json()
        pipes = {k: Pipeline.from_dir(getattr(pair, k).folder, cfg.provider, cfg.threads) for k in KINDS}
        for p in pipes.values():
            p.warmup()
        msd = pipes["msdnet"]
        points, source, frames = _inputs(cfg, msd)
        gate_note = choose_gate(msd, points, pair.msdnet.weights, _target(msd, cfg), cfg.seed)
        pipes["r2ldm"].gate = pipes["r2ldm"].artifact.gate  # R2LDM: its manifest's (usually dense)
        # the same scan by column name: an R2LDM may read fewer columns (as published: x y z only)
        named = {k: _named(points, msd.columns) if k != "msdnet" else points for k in KINDS}
        thr, thr_notes = {}, {}
        for k in KINDS:
            thr[k], thr_notes[k] = _threshold(pipes[k], getattr(pair, k).weights, named[k], cfg)
        log(f"timing MSDNet ({cfg.repeats} frames) ...")
        main = msdnet_timings(msd, points, thr["msdnet"], cfg.repeats, cfg.warmup, cfg.seed)
        sg = main["step_graph"]  # yardstick: the best sgemm rate seen in this run (load only slows it)
        sg["sgemm_gflops_peak"] = max(machine["sgemm_gflops"], sg["sgemm_gflops_adjacent"])
        sg["flops_over_peak"] = sg["gflops_rate_best"] / sg["sgemm_gflops_peak"]
        runs: StageRuns = main["runs"]
        flops = stage_flops(msd, points, thr["msdnet"], cfg.seed)  # on the timing input's own frame
        log(f"timing R2LDM ({cfg.r2ldm_repeats} frames) ...")
        r2 = time_stages(pipes["r2ldm"], named["r2ldm"], None, thr["r2ldm"], cfg.r2ldm_repeats, cfg.seed)
        main["step_graph"]["r2ldm_step_ms"] = summary(BareStep(pipes["r2ldm"]).seconds(3))["median"]
        steps_list = tuple(sorted(set(cfg.steps) | set(TABLE3_STEPS)))
        steps_rows = sweep(
            msd, thr["msdnet"], lambda s: (points, s), steps_list, "steps", cfg.sweep_repeats, cfg.seed
        )
        cols, grid = msd.columns, msd.artifact.grid

        def scaled(n: int) -> tuple[Any, None]:
            return synthetic_radar(cols, grid, n, cfg.seed + n), None

        scaling = sweep(msd, thr["msdnet"], scaled, cfg.point_counts, "points", cfg.sweep_repeats, cfg.seed)
        log("torch eager, voxelizer, msdnet-infer memory, INT8 ...")
        torch_res: dict[str, Any] = {"note": "no torch weights (the manifest's source checkpoint is gone)"}
        if pair.msdnet.torch_model is not None:
            ort_graphs = np.sum([runs.seconds[k] for k in GRAPH_STAGES], axis=0)  # per run
            torch_res = torch_comparison(
                pair.msdnet.torch_model,
                msd,
                points,
                ort_graphs,
                cfg.threads,
                min(3, cfg.sweep_repeats),
                cfg.seed,
            )
        log("coarse-to-fine vs dense head ...")
        c2f_gate = coarse_to_fine_gate(msd)
        head = head_comparison(msd, points, thr["msdnet"], max(5, cfg.sweep_repeats), cfg.seed, c2f_gate)
        peers: dict[str, Any] = {"note": "not run (--no-peers)"}
        if cfg.peers:
            log("peer engines per stage (OpenVINO, torch eager, torch.compile) ...")
            model, reps = pair.msdnet.torch_model, cfg.peer_repeats
            scans = _stream(cfg, msd, points, frames) if cfg.peer_stream else [points]
            peers = peer_comparison(model, msd, scans, cfg.threads, reps, cfg.seed, cfg.torch_compile)
        old: dict[str, Any] = {"note": "not run (--against-old: random models only)"}
        if cfg.against_old:
            log("the same model with its unoptimised graphs, interleaved ...")
            old = old_comparison(
                msd,
                points,
                thr["msdnet"],
                pair.cfg,
                scratch,
                cfg.threads,
                _target(msd, cfg),
                max(3, cfg.sweep_repeats),
                cfg.seed,
            )
        sensor, sensor_source = _frame_stream(cfg, msd, points, frames)
        stream: dict[str, Any] = {"source": sensor_source}
        if sensor:
            log(f"timing MSDNet on a stream ({len(sensor)} frames, each once) ...")
            stream |= stream_timings(msd, sensor, thr["msdnet"], cfg.seed, c2f_gate)
        before: dict[str, Any] = {"note": "not run (--before)"}
        if cfg.before is not None:
            before = _before(cfg, pair, msd, points, thr["msdnet"], sensor, sensor_source, log)
        vox = voxelize_figures(grid, len(cols), msd.artifact.inputs.max_voxels, max(10, cfg.repeats))
        rss = peak_rss_mb(pair.msdnet.folder, msd.select_columns(points), cols, cfg.threads, thr["msdnet"])
        int8 = {}
        if cfg.int8:
            int8 = int8_comparison(
                msd,
                points,
                thr["msdnet"],
                scratch,
                cfg.threads,
                max(5, cfg.repeats),
                cfg.sweep_repeats,
                cfg.seed,
            )
        quality = []
        if frames:
            from msdnet.benchmarks.latency.quality import quality_by_steps

            quality = quality_by_steps(msd, frames, TABLE3_STEPS, thr["msdnet"], cfg.seed)
    stages, r2_stages = runs.summaries(), r2.summaries()
    useful = efficiency(flops, stages, main["step_graph"]["sgemm_gflops_peak"])
    res: dict[str, Any] = {
        "preset": pair.cfg.preset,
        "head_kind": pair.cfg.head_kind,  # recon head: "dense", "gated" or "sparse"
        "up_sampling": cfg.up_sampling,  # random models' head export form (None: given models / default)
        "provider": cfg.provider,
        "threads": cfg.threads,
        "repeats": {"msdnet": cfg.repeats, "r2ldm": cfg.r2ldm_repeats, "sweeps": cfg.sweep_repeats},
        "machine": {**machine, "loadavg_start": list(load_start), "loadavg_end": list(os.getloadavg())},
        "input": {"source": source, **runs.stats},
        "models": {
            k: {
                "weights": getattr(pair, k).weights,
                "threshold": thr[k],
                "threshold_note": thr_notes[k],
                "steps": pipes[k].artifact.diffusion.sample_steps,
                "bev_shape": list(pipes[k].bev_shape),
                "gate": pipes[k].gate,
            }
            for k in KINDS
        },
        "decoded_points": {"msdnet": runs.decoded, "r2ldm": r2.decoded},
        "stages_ms": stages,
        "r2ldm_stages_ms": r2_stages,
        "stream": stream,
        "params": {k: getattr(pair, k).params for k in KINDS},
        "ratios": {
            "msdnet_over_r2ldm": stages["total"]["median"] / r2_stages["total"]["median"],
            "stream_over_repeated": (
                stream["stages_ms"]["total"]["median"] / stages["total"]["median"] if sensor else float("nan")
            ),
            "onnx_over_torch": torch_res.get("onnx_over_torch", float("nan")),
            "onnx_over_best_torch": torch_res.get("onnx_over_best_torch", float("nan")),
            "voxelize_numba_speedup": vox["speedup"],
            "voxelize_numba_speedup_100k": vox["speedup_100k"],
            "voxelize_rulebooks_numba_speedup": vox["speedup_with_rulebooks"],
            "loop_overhead_share": main["loop_overhead_share"],
            "step_flops_over_peak": main["step_graph"]["flops_over_peak"],
            "head_over_dense_head": head.get("head_over_dense_head", float("nan")),
            "head_over_dense_head_stream": stream.get("head_over_dense_head", float("nan")),
            "engine_over_best_peer": peers.get("engine_over_best_peer", float("nan")),
            "engine_over_best_f32_peer": peers.get("engine_over_best_f32_peer", float("nan")),
            "total_over_old_graphs": old.get("new_over_old", float("nan")),
            "frame_over_before": before.get("frame_over_before", float("nan")),
            "encoder_over_before": before.get("encoder_over_before", float("nan")),
        },
        "against_old": old,
        "before": before,
        "head": {**head, "gate_note": gate_note},
        "peers": peers,
        "provider_auto": {k: pipes[k].auto.to_json() for k in KINDS if pipes[k].auto is not None},
        "step_graph": main["step_graph"],
        "useful_flops": useful,
        "steps_sweep": steps_rows,
        "table3": {"steps": list(TABLE3_STEPS), "quality": quality},
        "points_scaling": scaling,
        "torch_eager": torch_res,
        "voxelize": vox,
        "peak_memory_mb": {"msdnet_infer": rss},
        "int8": int8,
    }
    res["notes"] = _notes(res)
    write_outputs(cfg.out, res)
    return res
