"""``--provider auto``'s measurements: seeded radar-like scans, the graph calls the pipeline
makes for them, every engine timed on them interleaved, and the checks that an engine's outputs
agree with onnxruntime's.

:func:`measure` times sessions on a stream of scans new to each timed session, within a hard
wall-clock budget (``BUDGET_S``; ``provider_budget`` says what it may still start); :func:`paired`
compares two engines' times scan by scan, and a rival wins when at least ``MARGIN`` faster.
``provider_agree.disagreement`` holds its outputs to the export tolerances (looser ``BF16_*`` ones
for bfloat16).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import onnxruntime as ort

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model import onnx_spec
from msdnet.runtime.providers import provider_agree
from msdnet.runtime.providers import provider_budget as budget

# a runtime.engine.pipeline.Pipeline; not imported, because the pipeline imports provider_auto
Pipeline = Any

ONNXRUNTIME, OPENVINO, OPENVINO_BF16 = "onnxruntime", "openvino", "openvino-bf16"
# where callers and tests look for them
AGREE_REL_TOL, AGREE_COS_TOL = provider_agree.AGREE_REL_TOL, provider_agree.AGREE_COS_TOL
AGREE_E2E_TOL = provider_agree.AGREE_E2E_TOL
align_rows, disagreement = provider_agree.align_rows, provider_agree.disagreement
MIN_TIMED_SCANS, WARMUP_ONCE_S = budget.MIN_TIMED_SCANS, budget.WARMUP_ONCE_S
BUDGET_S = 4.5  # s, wall clock: a first load's whole measurement (provider_budget), compiles included
STREAM_SCANS = 13  # at most this many distinct seeded scans: the first warms every engine up
STREAM_LOOP_STEPS = 4  # a scan's loop runs at most this many DDIM steps (the step graph: as many calls)
MARGIN = 0.03  # OpenVINO is picked only when at least this much faster (median of paired ratios)
SCAN_POINTS = 400  # points of the first scan; the others have 50 % to 150 % as many
SCAN_CLUSTERS = 12  # clumps of points in a seeded scan
SCAN_SPREAD = 0.015  # their standard deviation, as a share of the grid box on each axis


def failure_reason(err: Exception) -> str:
    """One line: OpenVINO's conversion summary (e.g. "No conversion rule found for operations:
    DeformConv-19") when it has one, else the first line of the message."""
    lines = [ln.strip(" -") for ln in str(err).splitlines() if ln.strip()]
    summary = [ln for ln in lines if ln.startswith(("No conversion rule", "Conversion is failed"))]
    return f"{type(err).__name__}: {'; '.join(summary or lines[:1])[:200]}"


def seeded_scan(pipe: Pipeline, rng: np.random.Generator, points: int = SCAN_POINTS) -> np.ndarray:
    """(points, C) float32 in the model's columns, radar-like: x, y, z in ``SCAN_CLUSTERS`` clumps
    whose centres are uniform over the grid box within the radar's field of view (``fov_deg`` either
    side of +x), spread ``SCAN_SPREAD`` of the box on each axis, clipped into the box; the other
    columns 0. A real frame's points lie on a few objects: on `astyx-lite` these scans leave the
    coarse-to-fine head about as many half-scale voxels as real frames do (median 2,856 against
    2,363 over 12 Astyx frames; uniform points over the box: about 7,000)."""
    grid = pipe.artifact.grid
    lo, hi = np.asarray(grid.point_range[:3], np.float32), np.asarray(grid.point_range[3:], np.float32)
    centres = np.empty((0, 3), np.float32)
    while len(centres) < SCAN_CLUSTERS:  # rejection sampling: the box always meets the field of view
        c = lo + (hi - lo) * rng.random((4 * SCAN_CLUSTERS, 3), dtype=np.float32)
        inside = np.abs(np.degrees(np.arctan2(c[:, 1], c[:, 0]))) <= grid.fov_deg
        centres = np.concatenate([centres, c[inside]])[:SCAN_CLUSTERS]
    xyz = centres[rng.integers(0, SCAN_CLUSTERS, points)]
    xyz += SCAN_SPREAD * (hi - lo) * rng.standard_normal((points, 3), dtype=np.float32)
    pts = np.zeros((points, len(pipe.columns)), np.float32)
    pts[:, :3] = np.clip(xyz, lo, np.nextafter(hi, lo))
    return pts


def scan_calls(
    pipe: Pipeline,
    pts: np.ndarray,
    noise: np.ndarray,
    sessions: dict[str, Any],
    steps: int | None = None,
) -> dict[str, list[dict[str, np.ndarray]]]:
    """Every graph call the pipeline makes for ``pts`` (N, C) float32 in the model's columns, the
    loop starting from ``noise`` (``pipe.bev_shape``), in order (the step graph: one call per step
    of ``steps``, None: the manifest's T_m; the coarse-to-fine head with the manifest's gate, 0.5
    without one), run through ``sessions`` with plain ``session.run``."""
    enc, _, _ = pipe.encoder_feeds(pts)
    calls: dict[str, list[dict[str, np.ndarray]]] = {onnx_spec.ENCODER.file: [enc]}
    (f_s,) = sessions[onnx_spec.ENCODER.file].run(None, enc)
    x = noise
    if pipe.kind == "student":
        calls[onnx_spec.RGFD_ADAPTER.file] = [{"bev_features": f_s, "noise": noise}]
        (x,) = sessions[onnx_spec.RGFD_ADAPTER.file].run(None, calls[onnx_spec.RGFD_ADAPTER.file][0])
    spec = onnx_spec.DENOISER_STEP if pipe.kind == "student" else onnx_spec.R2LDM_STEP
    calls[spec.file] = []
    for row in pipe.coefficients(steps):
        feed = {"x_t": x, "cond": f_s, "t": row[0:1], "abar_t": row[1:2], "abar_prev": row[2:3]}
        calls[spec.file].append({n: feed[n] for n in spec.inputs})
        (x,) = sessions[spec.file].run(None, calls[spec.file][-1])
    calls[onnx_spec.RECON_HEAD.file] = [{"features": x}]
    if onnx_spec.RECON_HEAD_SPARSE.file in pipe.sessions:
        gate = 0.5 if pipe.artifact.gate is None else pipe.artifact.gate
        calls[onnx_spec.RECON_HEAD_SPARSE.file] = [{"features": x, "gate": np.full(1, gate, np.float32)}]
    return calls


def frame_calls(
    pipe: Pipeline,
    seed: int = 0,
    points: int = SCAN_POINTS,
    sessions: dict[str, Any] | None = None,
    steps: int | None = None,
) -> dict[str, list[dict[str, np.ndarray]]]:
    """:func:`scan_calls` of one seeded scan of ``points`` points (:func:`seeded_scan`) through
    ``sessions`` (default: the pipeline's own)."""
    rng = np.random.default_rng(seed)
    pts = seeded_scan(pipe, rng, points)
    noise = rng.standard_normal(pipe.bev_shape, dtype=np.float32)
    return scan_calls(pipe, pts, noise, pipe.sessions if sessions is None else sessions, steps)


def graph_inputs(
    pipe: Pipeline, seed: int = 0, points: int = SCAN_POINTS, sessions: dict[str, Any] | None = None
) -> dict[str, dict[str, np.ndarray]]:
    """One call's inputs per graph of :func:`frame_calls` (the step graph: its middle step)."""
    return {f: c[len(c) // 2] for f, c in frame_calls(pipe, seed, points, sessions).items()}


def warm_voxelizer(pipe: Pipeline) -> threading.Thread:
    """Start loading the voxelizer's and rulebook builder's compiled code (numba: about a second in
    a new process, which the first scan would pay) in a thread, so that it overlaps OpenVINO's
    compiles; join it before :func:`measure`. A failure here is left for the first scan to report."""

    def load() -> None:
        try:
            pipe.encoder_feeds(seeded_scan(pipe, np.random.default_rng(0)))
        except Exception:  # noqa: BLE001, S110 - the first scan runs the same and reports it
            pass

    thread = threading.Thread(target=load, name="msdnet-auto-voxelizer", daemon=True)
    thread.start()
    return thread


def fresh_sessions(pipe: Pipeline, threads: int | None, files: list[str] | None = None) -> dict[str, Any]:
    """onnxruntime CPU sessions of the pipeline's graphs (``files``; None: all) that its own
    sessions do not share (what runs on them leaves the timed sessions unwarmed)."""
    from msdnet.runtime.providers.session import create_session

    names = list(pipe.sessions) if files is None else files
    return {f: create_session(pipe.artifact.graphs[f], f, "cpu", threads) for f in names}


def _loop_steps(pipe: Pipeline) -> int | None:
    """``STREAM_LOOP_STEPS`` when the manifest's loop makes more network calls (R2LDM's 128 steps
    would take minutes per load at paper size) and the schedule allows it, else None (its own)."""
    if pipe.coefficients().shape[0] <= STREAM_LOOP_STEPS:
        return None
    try:
        pipe.coefficients(STREAM_LOOP_STEPS)
    except MsdnetError:
        return None
    return STREAM_LOOP_STEPS


@dataclass
class _Bound:
    """An IOBinding with outputs bound like the pipeline's: static ones preallocated once and reused
    by every call (so no call pays for touching new pages), dynamic ones allocated per call."""

    binding: Any
    static: dict[str, ort.OrtValue]  # output name -> its buffer; the other outputs are dynamic
    names: list[str]  # output names, graph order

    @classmethod
    def of(cls, sess: Any, ref: list[np.ndarray]) -> _Bound:
        static = {
            o.name: ort.OrtValue.ortvalue_from_numpy(np.zeros_like(arr))  # pages touched: not in a timed call
            for o, arr in zip(sess.get_outputs(), ref, strict=True)
            if all(isinstance(d, int) for d in o.shape)
        }
        return cls(sess.io_binding(), static, [o.name for o in sess.get_outputs()])

    def feed(self, feed: dict[str, np.ndarray]) -> Any:
        """The binding with ``feed`` as its inputs and its outputs bound again."""
        b = self.binding
        for name, arr in feed.items():
            b.bind_ortvalue_input(name, ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(arr)))
        b.clear_binding_outputs()  # a dynamic output keeps the last call's shape otherwise
        for name in self.names:
            if name in self.static:
                b.bind_ortvalue_output(name, self.static[name])
            else:
                b.bind_output(name, "cpu")
        return b


WARMUP_CALLS = 2  # untimed runs of the first scan: a session's first call allocates its arena
HEAVY = {onnx_spec.RECON_HEAD_SPARSE.file: 1, onnx_spec.RECON_HEAD.file: 2}  # warmed up last, in this order


Calls = list[dict[str, np.ndarray]]  # one scan's calls of one graph, in order: input name -> array
Label = tuple[str, str]  # (graph file, engine): one timed session


@dataclass(frozen=True)
class Samples:
    """What :func:`measure` saw."""

    ms: dict[
        Label, np.ndarray
    ]  # (n,) ms of each of the first n timed scans' calls (n: scans, fewer if stopped)
    disagree: dict[Label, str]  # sessions whose outputs differ from onnxruntime's: why (one line)
    failed: dict[Label, str]  # sessions that raised on the scans: why (one line)
    scans: int  # scans timed after the warm-up
    deferred: tuple[str, ...] = ()  # graphs left untimed to keep to the budget (provider_budget)


def measure(pipe: Pipeline, runs: dict[Label, Any], threads: int | None, deadline: float) -> Samples:
    """Time every session of ``runs`` on a stream of seeded scans (:func:`seeded_scan`, seeds 0, 1,
    ...; the first of ``SCAN_POINTS`` points, the others of 0.5 to 1.5 times as many, in no order).
    Each scan's graph inputs come from throwaway onnxruntime sessions of the encoder, adapter and
    step graph, so no timed session has seen a scan before it is timed on it: OpenVINO prepares
    kernels per input shape, and a repeated input would flatter it. Scan 0 gives the reference
    outputs (the pipeline's own onnxruntime sessions) that every other engine is checked against,
    and warms every session up, graph by graph, the heads last (``HEAVY``): its first call (the
    reference, or the check) is the warm-up where it takes ``WARMUP_ONCE_S``, else ``WARMUP_CALLS``
    more. Then each
    further scan runs once per session, its calls back to back as the pipeline makes them (the step
    graph: one a loop step, at most ``STREAM_LOOP_STEPS``), sessions in an order rotated per scan,
    up to ``STREAM_SCANS`` in all, while the budget lasts: ``deadline`` (``time.perf_counter``) is
    hard, and ``provider_budget`` says which graphs are deferred, how many scans are timed whatever
    the budget, and which sessions stop early."""
    chain = [f for f in (onnx_spec.ENCODER.file, onnx_spec.RGFD_ADAPTER.file) if f in pipe.sessions]
    chain.append(onnx_spec.DENOISER_STEP.file if pipe.kind == "student" else onnx_spec.R2LDM_STEP.file)
    fresh = fresh_sessions(pipe, threads, chain)
    rest = np.linspace(SCAN_POINTS // 2, 3 * SCAN_POINTS // 2, STREAM_SCANS - 1).round().astype(int)
    counts = [SCAN_POINTS, *np.random.default_rng(0).permutation(rest)]  # sizes in no order
    steps = _loop_steps(pipe)
    t0 = time.perf_counter()
    first = frame_calls(pipe, 0, counts[0], fresh, steps)
    planned = time.perf_counter() - t0  # s: one timed scan (its inputs, the sessions kept), about
    files = sorted(dict.fromkeys(f for f, _ in runs), key=lambda f: HEAVY.get(f, 0))
    refs: dict[str, list[np.ndarray]] = {}
    live, disagree, failed, deferred = {}, {}, {}, []

    def run(label: Label, calls: Calls, bind: _Bound) -> None:
        for feed in calls:
            live[label].run_with_iobinding(bind.feed(feed))

    binds: dict[Label, _Bound] = {}
    kept, slow = False, False  # a graph is kept; the last one kept is slow
    for f in files:  # likely cheapest first
        labels = [label for label in runs if label[0] == f]
        # an engine pick (two engines) may wait for a later load, never the first one nor the head pick
        pick = kept and len(labels) > 1
        if pick and slow and not budget.fits(deadline, planned):  # no time even for its reference
            deferred.append(f)
            continue
        t0 = time.perf_counter()
        refs[f] = [np.asarray(a) for a in pipe.sessions[f].run(None, first[f][0])]
        call_s = time.perf_counter() - t0  # one call on onnxruntime, its first: about the cost
        slow, scan_s = call_s >= WARMUP_ONCE_S, call_s * len(first[f]) * len(labels)
        if budget.defer(pick and slow, deadline, planned, call_s * (len(labels) - 1), scan_s):
            deferred.append(f)
            continue
        kept = True
        for label in labels:
            sess, engine = runs[label], label[1]
            try:
                first_s = call_s if sess is pipe.sessions[f] else 0.0
                if engine != ONNXRUNTIME:
                    t0 = time.perf_counter()
                    names = [o.name for o in pipe.sessions[f].get_outputs()]
                    got = [np.asarray(a) for a in sess.run(None, first[f][0])]
                    first_s = time.perf_counter() - t0
                    why = disagreement(got, refs[f], names, getattr(sess, "precision", "f32"))
                    if why is not None:
                        disagree[label] = why
                binds[label] = _Bound.of(sess, refs[f])
                live[label] = sess
                planned += max(first_s, call_s) * len(first[f])
                for _ in range(0 if first_s >= WARMUP_ONCE_S else WARMUP_CALLS):
                    t0 = time.perf_counter()
                    run(label, first[f], binds[label])
                    if time.perf_counter() - t0 >= WARMUP_ONCE_S:
                        break
            except Exception as err:  # noqa: BLE001 - an engine failing on these inputs: not timed
                failed[label] = failure_reason(err)
                live.pop(label, None)
    live = {label: live[label] for label in runs if label in live}  # the order of runs
    samples: dict[Label, list[float]] = {label: [] for label in live}
    stopped: set[Label] = set()  # clearly slower than the other engine: no longer timed
    scans, scan_s = 0, planned
    for k in range(1, STREAM_SCANS):
        if not live or (scans >= budget.scan_floor(scan_s) and not budget.fits(deadline, scan_s)):
            break
        t_scan = time.perf_counter()
        scan = frame_calls(pipe, k, int(counts[k]), fresh, steps)
        order = [label for label in live if label not in stopped]
        for label in order[k % max(len(order), 1) :] + order[: k % max(len(order), 1)]:
            t0 = time.perf_counter()
            try:
                run(label, scan[label[0]], binds[label])
            except Exception as err:  # noqa: BLE001 - as above
                failed[label] = failure_reason(err)
                live.pop(label)
                samples.pop(label)
                continue
            samples[label].append(time.perf_counter() - t0)
        scans, scan_s = k, time.perf_counter() - t_scan
        if not budget.fits(deadline, scan_s * (STREAM_SCANS - 1 - k)):  # the stream will not end in time
            stopped |= budget.clearly_slower(samples, disagree)
    pipe.coefficients()  # a sampler keeps the last plan's re-noising: the manifest's again
    ms = {label: np.asarray(v) * 1e3 for label, v in samples.items()}
    return Samples(ms, disagree, failed, scans, tuple(deferred))


def paired(calls: dict[str, np.ndarray], over: str, under: str) -> tuple[dict[str, float], float]:
    """(median ms a scan by engine, median over the scans of ``over``'s time / ``under``'s) of
    :func:`measure`'s samples: paired by scan, because the scans differ in size and both ran
    each one back to back; over the scans all of them ran (a session stopped early ran fewer)."""
    n = min(len(v) for v in calls.values())
    medians = {e: float(np.median(v[:n])) for e, v in calls.items()}
    return medians, float(np.median(calls[over][:n] / calls[under][:n]))
