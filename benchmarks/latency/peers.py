"""The engines a user could pick instead of ours, on the same graphs, inputs and threads, per stage.

Stages are the pipeline's graph stages: ``encoder``, ``rgfd_adapter`` (MSDNet only), ``ddim_loop``
(every step of one frame, the recorded loop states as inputs) and ``recon_head`` (the graph the
pipeline runs: the coarse-to-fine ``recon_head_sparse.onnx`` with its gate, or the dense head).
Engines:

- ``onnxruntime``: ours, the pipeline's own sessions (its threads and provider: with
  ``--provider openvino`` or ``auto`` some of them are OpenVINO's), plain ``session.run``. Where
  ours is an OpenVINO session it is the ``openvino`` (or ``openvino_bf16``) peer itself, same
  graph, precision and settings, so that peer's calls are ours too (``ours_is``): timed twice, the
  one running second would find the kernels the first prepared for each new input shape;
- ``openvino``: the same ONNX bytes compiled for the CPU as ``--provider openvino`` does
  (``runtime.providers.openvino_session``: ``threads`` inference threads, f32; the optional ``[openvino]``
  extra); a graph it cannot load (``rgfd_adapter.onnx``: no DeformConv in its ONNX front end) is
  reported with the reason;
- ``openvino_bf16``: the same compiled in bfloat16 (``--provider openvino-bf16``), on CPUs whose
  OpenVINO lists BF16 (else reported with the reason): the peer to beat when ours runs
  ``--provider auto-bf16``;
- ``torch_eager``: the torch modules the graphs were exported from (``export.graphs.graph_modules``:
  the checkpoint's weights, or the random weights of the exported random model),
  ``torch.set_num_threads(threads)``, ``inference_mode``;
- ``torch_compile``: the same modules through ``torch.compile`` (compiled during the warm-up).

The input is a stream, as a sensor gives: ``scans[0]`` warms every engine up (twice), then repeat
r runs the stage inputs of ``scans[1 + r % (len(scans) - 1)]``, so with ``repeats + 1`` scans no
engine sees an input twice. The inputs are made on throwaway onnxruntime sessions, so ours have
not seen them either. That matters for OpenVINO, which prepares its kernels per input shape (the
encoder's voxel and rulebook counts and the sparse head's gated voxels change every frame): on one
frame repeated it is faster than on a stream. One scan: that
frame repeated. Every repeat runs each engine once per stage,
interleaved (the order rotated per repeat), so all see the same load. A peer's
total is the sum of its stage medians, with onnxruntime's median standing in for a stage it cannot
run (listed in ``substituted``). ``engine_over_best_peer`` = ours / the fastest peer, per stage and
for the total (<= 1: ours is the fastest); ``engine_over_best_f32_peer`` the same against the
full-precision peers only.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from msdnet.benchmarks.latency.head import coarse_to_fine_gate
from msdnet.benchmarks.latency.peer_report import OTHER_HEAD  # the head graph ours does not run
from msdnet.benchmarks.latency.timing import Scan
from msdnet.runtime.engine.pipeline import Pipeline
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.providers.provider_measure import failure_reason, fresh_sessions, scan_calls

ENGINES = ("onnxruntime", "openvino", "openvino_bf16", "torch_eager", "torch_compile")
REDUCED_PRECISION = ("openvino_bf16",)  # peers that do not compute in f32
Feeds = list[dict[str, np.ndarray]]  # one dict per graph call, contract input names -> arrays


def stage_specs(pipe: Pipeline) -> dict[str, onnx_spec.GraphSpec]:
    """Stage -> the graph the pipeline runs for it (the head: sparse when ``pipe.gate`` is set)."""
    out = {"encoder": onnx_spec.ENCODER}
    if pipe.kind == "student":
        out["rgfd_adapter"] = onnx_spec.RGFD_ADAPTER
    out["ddim_loop"] = onnx_spec.DENOISER_STEP if pipe.kind == "student" else onnx_spec.R2LDM_STEP
    out["recon_head"] = onnx_spec.RECON_HEAD if pipe.gate is None else onnx_spec.RECON_HEAD_SPARSE
    return out


def other_head(pipe: Pipeline) -> tuple[onnx_spec.GraphSpec, float] | None:
    """The head graph the pipeline does not run and the coarse-to-fine gate, when it has both heads
    and a gate (``pipe.gate``, else the manifest's: ``--provider auto`` may run the dense head)."""
    gate = coarse_to_fine_gate(pipe)
    files = (onnx_spec.RECON_HEAD.file, onnx_spec.RECON_HEAD_SPARSE.file)
    if pipe.kind != "student" or gate is None or not all(f in pipe.sessions for f in files):
        return None
    return (onnx_spec.RECON_HEAD if pipe.gate is not None else onnx_spec.RECON_HEAD_SPARSE), gate


def peer_specs(pipe: Pipeline) -> dict[str, onnx_spec.GraphSpec]:
    """:func:`stage_specs` and, where there is one, ``recon_head_other``: the other head graph,
    which a user of a peer engine may find faster there (a peer's total counts its faster head)."""
    other = other_head(pipe)
    return stage_specs(pipe) | ({} if other is None else {OTHER_HEAD: other[0]})


def capture_feeds(
    pipe: Pipeline, points: Scan, seed: int = 0, sessions: dict[str, Any] | None = None
) -> dict[str, Feeds]:
    """Every graph input of one frame per stage of :func:`peer_specs` (``provider_measure.scan_calls``:
    the pipeline's arithmetic with plain ``session.run`` on ``sessions``, default the pipeline's
    own; the coarse-to-fine head with ``pipe.gate``, or the manifest's when it runs the dense one)."""
    noise = np.random.default_rng(seed).standard_normal(pipe.bev_shape, dtype=np.float32)
    sessions = pipe.sessions if sessions is None else sessions
    calls = scan_calls(pipe, pipe.select_columns(points), noise, sessions)
    feeds = {stage: calls[spec.file] for stage, spec in stage_specs(pipe).items() if stage != "recon_head"}
    features = calls[onnx_spec.RECON_HEAD.file][0]["features"]
    other = other_head(pipe)
    for stage, spec in peer_specs(pipe).items():
        if stage in ("recon_head", OTHER_HEAD):
            head: dict[str, np.ndarray] = {"features": features}
            if spec.file == onnx_spec.RECON_HEAD_SPARSE.file:
                head["gate"] = np.full(1, pipe.gate if other is None else other[1], np.float32)
            feeds[stage] = [head]
    return feeds


Runner = Callable[[Feeds], None]  # runs one stage's graph calls of one frame


def _onnxruntime(pipe: Pipeline, spec: onnx_spec.GraphSpec) -> Runner:
    sess = pipe.sessions[spec.file]

    def run(feeds: Feeds) -> None:
        for f in feeds:
            sess.run(None, f)

    return run


def _openvino(pipe: Pipeline, spec: onnx_spec.GraphSpec, threads: int, precision: str = "f32") -> Runner:
    from msdnet.runtime.providers.openvino_session import OpenVinoSession
    from msdnet.runtime.providers.session import openvino_has_bf16

    if precision == "bf16" and not openvino_has_bf16():
        raise RuntimeError("OpenVINO has no bfloat16 on this CPU (no BF16 capability)")
    # as --provider openvino (f32) or openvino-bf16
    sess = OpenVinoSession(pipe.artifact.graphs[spec.file], threads, precision)

    def run(feeds: Feeds) -> None:
        for f in feeds:
            sess.run(None, f)

    return run


def _torch(module: torch.nn.Module, spec: onnx_spec.GraphSpec) -> Runner:
    def run(feeds: Feeds) -> None:
        args = [tuple(torch.from_numpy(np.ascontiguousarray(f[n])) for n in spec.inputs) for f in feeds]
        with torch.inference_mode():
            for a in args:
                module(*a)

    return run


def _same_peer(sess: Any) -> str | None:
    """The peer engine that ``sess`` (one of the pipeline's sessions) is: ``openvino`` or
    ``openvino_bf16`` for an OpenVINO session, None for onnxruntime's."""
    precision = getattr(sess, "precision", None)  # runtime.providers.openvino_session.OpenVinoSession
    return None if precision is None else {"f32": "openvino", "bf16": "openvino_bf16"}[precision]


def _modules(model: torch.nn.Module, kind: str) -> dict[str, torch.nn.Module]:
    from msdnet.export.graphs import graph_modules

    return {spec.file: mod.eval() for spec, mod in graph_modules(model, kind)}


def peer_comparison(
    model: torch.nn.Module | None,
    pipe: Pipeline,
    scans: list[Scan],
    threads: int,
    repeats: int,
    seed: int = 0,
    compile_torch: bool = True,
) -> dict[str, Any]:
    """Per stage and engine: median / p90 / min ms (interleaved repeats over the stream ``scans``),
    engines that could not run a stage with the reason, totals and ``engine_over_best_peer``
    (module docstring)."""
    if not scans:
        raise ValueError("peer_comparison needs at least one scan")
    fresh = fresh_sessions(pipe, threads)
    frames = [capture_feeds(pipe, s, seed, fresh) for s in scans]
    timed = list(range(1, len(frames))) or [0]  # one scan: that frame, repeated
    specs = peer_specs(pipe)
    mods = _modules(model, pipe.kind) if model is not None else {}
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    runners: dict[str, dict[str, Runner]] = {s: {} for s in specs}
    failed: dict[str, dict[str, str]] = {s: {} for s in specs}
    ours_is = {s: _same_peer(pipe.sessions[spec.file]) for s, spec in specs.items()}
    try:
        for stage, spec in specs.items():
            makers: dict[str, Callable[[], Runner]] = {
                "onnxruntime": lambda spec=spec: _onnxruntime(pipe, spec),
                "openvino": lambda spec=spec: _openvino(pipe, spec, threads),
                "openvino_bf16": lambda spec=spec: _openvino(pipe, spec, threads, "bf16"),
            }
            if spec.file in mods:
                mod = mods[spec.file]
                makers["torch_eager"] = lambda mod=mod, spec=spec: _torch(mod, spec)
                makers["torch_compile"] = lambda mod=mod, spec=spec: _torch(torch.compile(mod), spec)
            for engine in ENGINES:
                if engine == "onnxruntime" and ours_is[stage]:
                    continue  # that peer's calls are ours (module docstring)
                if engine == "torch_compile" and not compile_torch:
                    failed[stage][engine] = "not run (--no-torch-compile)"
                    continue
                if engine not in makers:
                    failed[stage][engine] = "no torch weights (the manifest's source checkpoint is gone)"
                    continue
                try:
                    fn = makers[engine]()
                    fn(frames[0][stage])  # warm-up (torch.compile compiles here)
                    fn(frames[0][stage])
                except Exception as err:  # noqa: BLE001 - any engine failure is a result to report
                    failed[stage][engine] = failure_reason(err)
                    continue
                runners[stage][engine] = fn
        seconds: dict[str, dict[str, list[float]]] = {s: {e: [] for e in runners[s]} for s in specs}
        for r in range(repeats):  # interleaved: every engine sees the same load
            feeds = frames[timed[r % len(timed)]]
            for stage in specs:
                # rotated per repeat: whoever runs right after torch (whose OpenMP pool keeps
                # spinning for a while) takes that hit in turn, not always the same engine
                order = list(runners[stage].items())
                order = order[r % len(order) :] + order[: r % len(order)] if order else order
                for engine, fn in order:
                    t0 = time.perf_counter()
                    fn(feeds[stage])
                    seconds[stage][engine].append(time.perf_counter() - t0)
    finally:
        torch.set_num_threads(before)
    for stage, peer in ours_is.items():
        if peer and seconds[stage].get(peer):
            seconds[stage]["onnxruntime"] = list(seconds[stage][peer])
        elif peer:
            failed[stage]["onnxruntime"] = f"ours is the {peer} peer, which did not run"
    out = _table(specs, seconds, failed, threads, repeats)
    for stage, peer in ours_is.items():
        out["stages"][stage]["ours_is"] = peer
    distinct = min(repeats, len(timed))
    out["input"] = (
        f"a stream: {distinct} distinct frames timed, each engine seeing each once"
        if len(frames) > 1 and distinct == repeats
        else f"{distinct} distinct frame(s) over {repeats} repeats (one frame: repeated)"
    )
    return out


def _peer_ms(stages: dict[str, Any], stage: str, engine: str) -> float:
    """A peer's median ms for ``stage``; for the head, the faster of its two head graphs."""
    ms = stages[stage][engine]["median"]
    if stage == "recon_head" and engine in stages.get(OTHER_HEAD, {}):
        ms = min(ms, stages[OTHER_HEAD][engine]["median"])
    return ms


def _table(
    specs: dict[str, onnx_spec.GraphSpec],
    seconds: dict[str, dict[str, list[float]]],
    failed: dict[str, dict[str, str]],
    threads: int,
    repeats: int,
) -> dict[str, Any]:
    from msdnet.benchmarks.latency.timing import summary

    stages: dict[str, Any] = {}
    for stage, spec in specs.items():
        row: dict[str, Any] = {"graph": spec.file}
        row |= {e: summary(v) for e, v in seconds[stage].items()}
        row["failed"] = failed[stage]
        stages[stage] = row
    for stage, row in stages.items():
        # a peer's head: the faster of its two head graphs; ours: the one it runs
        peers = {e: _peer_ms(stages, stage, e) for e in ENGINES[1:] if e in row}
        if "onnxruntime" in row and peers and stage != OTHER_HEAD:
            row["best_peer"] = min(peers, key=peers.get)
            row["engine_over_best_peer"] = row["onnxruntime"]["median"] / peers[row["best_peer"]]
    totals: dict[str, Any] = {}
    for engine in ENGINES:
        if all(engine not in stages[s] for s in specs):
            continue
        ms, subs = 0.0, []
        for stage in (s for s in specs if s != OTHER_HEAD):
            if engine in stages[stage]:
                ms += (
                    stages[stage][engine]["median"]
                    if engine == "onnxruntime"
                    else _peer_ms(stages, stage, engine)
                )
            else:
                ms += stages[stage].get("onnxruntime", {}).get("median", float("nan"))
                subs.append(stage)
        totals[engine] = {"median_ms": ms, "substituted": subs}
    ours = totals.get("onnxruntime", {}).get("median_ms", float("nan"))
    peer_totals = {e: t["median_ms"] for e, t in totals.items() if e != "onnxruntime"}
    best = min(peer_totals, key=peer_totals.get) if peer_totals else None
    f32 = {e: v for e, v in peer_totals.items() if e not in REDUCED_PRECISION}
    best_f32 = min(f32, key=f32.get) if f32 else None
    return {
        "threads": threads,
        "repeats": repeats,
        "stages": stages,
        "totals": totals,
        "best_peer": best,
        "engine_over_best_peer": ours / peer_totals[best] if best else float("nan"),
        "best_f32_peer": best_f32,
        "engine_over_best_f32_peer": ours / f32[best_f32] if best_f32 else float("nan"),
    }
