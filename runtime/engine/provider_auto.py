"""``--provider auto``: per graph, the faster of onnxruntime (CPU provider) and OpenVINO here.

At load (``Pipeline(artifact, "auto")``) every graph is first opened on onnxruntime; its inputs
are then the model's own: ``STREAM_SCANS`` seeded radar-like scans (points in clumps in the
field of view), of different point counts, each through the pipeline's voxelizer and rulebooks,
the encoder, the adapter (MSDNet) and the loop (the manifest's T_m, at most
``STREAM_LOOP_STEPS``) on throwaway onnxruntime sessions (so the timed ones have seen none of
them); each graph keeps the calls each scan made of it (the step graph: one a step; the
coarse-to-fine head: with the manifest's gate, 0.5 without one). Each engine runs the first
scan's calls untimed, then every other scan's once, back to back as the
pipeline makes them, engines interleaved (order rotated per scan), outputs bound as the pipeline
binds them: a stream of inputs it has not seen, as a sensor gives. That matters: OpenVINO
prepares its kernels for each new input shape (the encoder's voxel and rulebook counts and the
sparse head's gated voxels change every frame), so on a graph called again and again on one
input it is faster than on a stream (``astyx-lite``, 2 threads, 440 Astyx frames in order: 24.5
ms a frame with the picks timed on one repeated input, 22.3 on onnxruntime alone;
``docs/results/latency-twelfth``). Each graph keeps:

- OpenVINO when its time over onnxruntime's for the same scan, median over the scans, is at most
  1 - ``MARGIN`` *and* its outputs agree with onnxruntime's within the export tolerances
  (``AGREE_REL_TOL``, ``AGREE_COS_TOL``, and for the coarse-to-fine head's gated voxels
  ``AGREE_E2E_TOL``: the values of ``export.verify``); else onnxruntime (near ties stay on the
  default engine);
- onnxruntime, with the reason, for a graph OpenVINO cannot load (``rgfd_adapter.onnx``: no
  DeformConv in its ONNX front end) or when OpenVINO is not installed.

Then, when the manifest has a gate, ``provider_head`` picks the head graph: the dense head when it
is faster on its engine than the coarse-to-fine head on its engine (its outputs are the reference
the gated head approximates).

``auto-bf16`` is the same contest with OpenVINO compiling in bfloat16 (engine ``openvino-bf16``):
its outputs are held to the looser ``BF16_*`` tolerances (bf16 keeps about 3 significant digits),
and what that costs in CD and F-score is measured end to end by ``msdnet-bench steps``.

Picks are cached in ``$XDG_CACHE_HOME/msdnet/providers.json`` (default ``~/.cache``), one entry
per graph keyed by the model hash (sha256 of the manifest, which lists every graph's sha256 and
the gate), the graph, its threads, the CPU model and core count and both library versions; the
file is rewritten atomically (temporary file, then ``os.replace``) and one that cannot be read
is replaced. An unwritable cache only costs a measurement per process. Within a process picks
are also kept in memory. Outputs are within the export tolerances of ``--provider cpu``, not
byte-equal to them: ``cpu`` stays the byte-reproducible default.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import platform
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from msdnet.runtime.errors import MsdnetError
from msdnet.runtime.model import onnx_spec

# a runtime.engine.pipeline.Pipeline; not imported, because the pipeline imports this module
Pipeline = Any

ONNXRUNTIME, OPENVINO, OPENVINO_BF16 = "onnxruntime", "openvino", "openvino-bf16"
STREAM_SCANS = 13  # distinct seeded scans: the first warms each engine up, the others are timed once
STREAM_LOOP_STEPS = 4  # a scan's loop runs at most this many DDIM steps (the step graph: as many calls)
MARGIN = 0.03  # OpenVINO is picked only when at least this much faster (median of paired ratios)
AGREE_REL_TOL = 1e-4  # = export.verify.GRAPH_REL_TOL (tests/test_provider_auto.py checks)
AGREE_COS_TOL = 1e-6  # = export.verify.GRAPH_COS_TOL
AGREE_E2E_TOL = 0.002  # = export.verify.E2E_DIFF_TOL: voxels gated by one engine only (sparse head)
# auto-bf16: OpenVINO in bfloat16 against onnxruntime f32, a guard against a broken conversion
# (a wrong graph is off by O(1)), not a quality bound. Shipped astyx-lite, measured: dense head
# occupancy max rel 3.5e-2, cosine 0.9998; coarse-to-fine head: 78 of 3021 gated voxels flip.
BF16_REL_TOL = 0.1
BF16_COS_TOL = 1e-3
BF16_E2E_TOL = 0.05
CACHE_VERSION = 3  # 1: picks timed on one repeated input (favoured OpenVINO); 2: step graph call by call
SCAN_POINTS = 400  # points of the first scan; the others have 50 % to 150 % as many
SCAN_CLUSTERS = 12  # clumps of points in a seeded scan
SCAN_SPREAD = 0.015  # their standard deviation, as a share of the grid box on each axis
_MEMO: dict[str, dict[str, Any]] = {}  # cache key -> entry, this process


@dataclass(frozen=True)
class EnginePick:
    """The engine ``auto`` runs one graph on, and why."""

    graph: str  # graph file name
    engine: str  # ONNXRUNTIME, OPENVINO or OPENVINO_BF16
    ms: dict[str, float] = field(default_factory=dict)  # median ms a scan by engine (measured ones)
    reason: str = ""  # one line: the comparison, or why OpenVINO was not an option
    cached: bool = False  # taken from the cache (measured by an earlier load)
    ratio: float | None = None  # OpenVINO / onnxruntime, median over the scans; None: not timed

    def line(self) -> str:
        times = ", ".join(f"{e} {v:.3f} ms" for e, v in self.ms.items())
        source = "cached" if self.cached else "measured"
        return f"{self.graph}: {self.engine} ({times + '; ' if times else ''}{self.reason}; {source})"

    def to_json(self) -> dict[str, Any]:
        out = {"engine": self.engine, "ms": dict(self.ms), "reason": self.reason, "cached": self.cached}
        return out | {"ratio": self.ratio}


@dataclass(frozen=True)
class AutoReport:
    """Every graph's pick and where the cache is."""

    picks: dict[str, EnginePick]  # graph file -> pick, in pipeline order
    cache: Path  # the cache file
    cache_note: str  # "read", "written" or why it was not written
    head: Any = None  # provider_head.HeadPick: the coarse-to-fine or the dense head; None: no contest

    @property
    def dense_head(self) -> bool:
        """The head pick is the dense head: the pipeline runs it with no gate."""
        return self.head is not None and self.head.head == "dense"

    def lines(self) -> list[str]:
        head = [] if self.head is None else [f"provider auto: {self.head.line()}"]
        return (
            [f"provider auto: {p.line()}" for p in self.picks.values()]
            + head
            + [f"provider auto: cache {self.cache} ({self.cache_note})"]
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "picks": {f: p.to_json() for f, p in self.picks.items()},
            "head": None if self.head is None else self.head.to_json(),
            "cache": cache_shown(self.cache),
            "cache_note": self.cache_note,
        }


def cache_shown(cache: Path) -> str:
    """``cache`` as results documents record it: under ``$XDG_CACHE_HOME`` or ``~`` named so, not by
    the machine's folders."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    for root, name in ((base, "$XDG_CACHE_HOME"), (str(Path.home()), "~")):
        if root and Path(root).is_absolute():
            try:
                return f"{name}/{cache.relative_to(root).as_posix()}"
            except ValueError:
                continue
    return cache.name


def cache_path() -> Path:
    """``$XDG_CACHE_HOME/msdnet/providers.json``; ``~/.cache`` when unset or not absolute."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    root = Path(base) if base and Path(base).is_absolute() else Path.home() / ".cache"
    return root / "msdnet" / "providers.json"


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``, else ``platform``) and logical core count."""
    name = ""
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace").splitlines():
            if line.lower().startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{name or platform.processor() or platform.machine()} x{os.cpu_count()}"


def openvino_version() -> str | None:
    """The installed OpenVINO's version, None when it is not installed."""
    if importlib.util.find_spec("openvino") is None:
        return None
    import openvino as ov

    return str(ov.__version__)


def model_hash(manifest: dict[str, Any]) -> str:
    """sha256 of the manifest (canonical JSON): it lists every graph's sha256 and the gate."""
    return hashlib.sha256(json.dumps(manifest, sort_keys=True).encode()).hexdigest()


def cache_key(manifest: dict[str, Any], graph: str, threads: int | None, precision: str = "f32") -> str:
    ov = openvino_version() or "none"
    parts = [model_hash(manifest), graph, f"threads {threads or 'default'}", cpu_model()]
    if precision != "f32":  # f32 keys stay as they were, so existing caches still hold
        parts.append(f"openvino {precision}")
    return " | ".join([*parts, f"onnxruntime {ort.__version__}", f"openvino {ov}"])


def read_cache(path: Path) -> dict[str, dict[str, Any]]:
    """The cache's entries; empty when the file is missing, unreadable or of another version."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    ok = (
        isinstance(doc, dict) and doc.get("version") == CACHE_VERSION and isinstance(doc.get("entries"), dict)
    )
    return doc["entries"] if ok else {}


def write_cache(path: Path, new: dict[str, dict[str, Any]]) -> str:
    """Merge ``new`` into the cache file atomically; -> "written" or why not (one line)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        entries = {**read_cache(path), **new}
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".providers-", suffix=".tmp")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump({"version": CACHE_VERSION, "entries": entries}, f, indent=1, sort_keys=True)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as err:
        return f"not written: {type(err).__name__}: {err.strerror or err}"
    return "written"


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
    if onnx_spec.RECON_HEAD_SPARSE.file in sessions:
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
    """:func:`scan_calls` of one seeded scan of ``points`` points (module docstring) through
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


@dataclass(frozen=True)
class StreamInputs:
    """What every graph is timed on: ``STREAM_SCANS`` scans' calls and the outputs they give."""

    feeds: list[dict[str, list[dict[str, np.ndarray]]]]  # per scan: graph file -> its calls' inputs
    outputs: list[dict[str, list[list[np.ndarray]]]]  # per scan: graph file -> onnxruntime's outputs


def stream_inputs(pipe: Pipeline, threads: int | None, first_seed: int = 0) -> StreamInputs:
    """The scans of the module docstring (``STREAM_SCANS``, seeds ``first_seed``, +1, ...: seed 0
    is :func:`graph_inputs`'s default; the first of ``SCAN_POINTS``, the others of ``SCAN_POINTS``
    x 0.5 to 1.5 points), run on throwaway onnxruntime sessions so that the pipeline's own have
    seen none of them."""
    fresh = fresh_sessions(pipe, threads)
    rest = np.linspace(SCAN_POINTS // 2, 3 * SCAN_POINTS // 2, STREAM_SCANS - 1).round().astype(int)
    counts = [SCAN_POINTS, *np.random.default_rng(first_seed).permutation(rest)]  # sizes in no order
    steps = _loop_steps(pipe)
    feeds = [frame_calls(pipe, first_seed + k, int(n), fresh, steps) for k, n in enumerate(counts)]
    outputs = [{f: [fresh[f].run(None, c) for c in cs] for f, cs in scan.items()} for scan in feeds]
    pipe.coefficients()  # a sampler keeps the last plan's re-noising: the manifest's again
    return StreamInputs(feeds, outputs)


def fresh_sessions(pipe: Pipeline, threads: int | None) -> dict[str, Any]:
    """onnxruntime CPU sessions of the pipeline's graphs that its own sessions do not share (what
    runs on them leaves the timed sessions unwarmed)."""
    from msdnet.runtime.engine.session import create_session

    return {f: create_session(pipe.artifact.graphs[f], f, "cpu", threads) for f in pipe.sessions}


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
            o.name: ort.OrtValue.ortvalue_from_numpy(np.empty_like(arr))
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


Calls = list[dict[str, np.ndarray]]  # one scan's calls of one graph, in order: input name -> array


def time_engines(
    sessions: dict[str, Any],
    scans: list[Calls] | dict[str, list[Calls]],
    refs: list[list[list[np.ndarray]]] | dict[str, list[list[list[np.ndarray]]]],
) -> dict[str, np.ndarray]:
    """ms each engine takes for each scan's calls but the first scan's, over a stream: ``scans[0]``
    untimed (``WARMUP_CALLS`` times), then every other scan once per engine, its calls back to
    back as the pipeline makes them (the step graph: one a loop step), engines interleaved, order
    rotated per scan. ``scans`` and ``refs`` (each call's outputs, for binding them): one list for
    every session, or one per session (sessions of different graphs, ``provider_head``)."""
    names = list(sessions)
    feeds = scans if isinstance(scans, dict) else dict.fromkeys(names, scans)
    outs = refs if isinstance(refs, dict) else dict.fromkeys(names, refs)
    binds = {e: _Bound.of(s, outs[e][0][0]) for e, s in sessions.items()}

    def run(e: str, calls: Calls) -> None:
        for feed in calls:
            sessions[e].run_with_iobinding(binds[e].feed(feed))

    for e in names:
        for _ in range(WARMUP_CALLS):
            run(e, feeds[e][0])
    samples: dict[str, list[float]] = {e: [] for e in names}
    for k in range(1, len(feeds[names[0]])):
        for e in names[k % len(names) :] + names[: k % len(names)]:
            t0 = time.perf_counter()
            run(e, feeds[e][k])
            samples[e].append(time.perf_counter() - t0)
    return {e: np.asarray(v) * 1e3 for e, v in samples.items()}


def align_rows(
    got: list[np.ndarray], ref: list[np.ndarray], names: list[str], e2e_tol: float = AGREE_E2E_TOL
) -> tuple[list, list, str | None]:
    """The coarse-to-fine head's outputs (one row per gated voxel, ``voxels`` its ids) on the
    voxels both engines gated: a voxel whose occupancy sits on the gate may fall on either side.
    Up to ``e2e_tol`` of the voxels may be gated by one engine only; else why (one line)."""
    if "voxels" not in names or all(a.shape == b.shape for a, b in zip(got, ref, strict=True)):
        return got, ref, None
    k = names.index("voxels")
    common, ia, ib = np.intersect1d(got[k], ref[k], return_indices=True)
    only = len(got[k]) + len(ref[k]) - 2 * len(common)
    if only > e2e_tol * max(len(got[k]), len(ref[k])):
        return got, ref, f"outputs differ from onnxruntime's: {only} of {len(ref[k])} gated voxels"
    return [a[ia] for a in got], [b[ib] for b in ref], None


def disagreement(
    got: list[np.ndarray], ref: list[np.ndarray], names: list[str] | None = None, precision: str = "f32"
) -> str | None:
    """None when every output agrees within the export tolerances (``precision`` bf16: the
    ``BF16_*`` ones), else why (one line). With ``names`` (output names), gated rows are matched
    first (:func:`align_rows`)."""
    bf16 = precision == "bf16"
    rel_tol, cos_tol = (BF16_REL_TOL, BF16_COS_TOL) if bf16 else (AGREE_REL_TOL, AGREE_COS_TOL)
    got, ref, why = align_rows(got, ref, names or [], BF16_E2E_TOL if bf16 else AGREE_E2E_TOL)
    if why is not None:
        return why
    for a, b in zip(got, ref, strict=True):
        if a.shape != b.shape:
            return f"outputs differ from onnxruntime's: shape {a.shape} != {b.shape}"
        x, y = a.astype(np.float64).ravel(), b.astype(np.float64).ravel()
        if not x.size:
            continue
        diff, scale = float(np.max(np.abs(x - y))), float(np.max(np.abs(y)))
        rel = diff / scale if scale > 0 else diff
        norm = float(np.linalg.norm(x) * np.linalg.norm(y))
        cos = float(x @ y / norm) if norm > 0 else (1.0 if diff == 0 else 0.0)
        if rel > rel_tol or cos < 1.0 - cos_tol:
            return f"outputs differ from onnxruntime's: max rel {rel:.2e}, cosine {cos:.9f}"
    return None


def paired(calls: dict[str, np.ndarray], over: str, under: str) -> tuple[dict[str, float], float]:
    """(median ms a scan by engine, median over the scans of ``over``'s time / ``under``'s) of
    :func:`time_engines`' samples: paired by scan, because the scans differ in size and both ran
    each one back to back."""
    return {e: float(np.median(v)) for e, v in calls.items()}, float(np.median(calls[over] / calls[under]))


def _measure(pipe: Pipeline, file: str, ov: Any, stream: StreamInputs) -> dict[str, Any]:
    feeds = [scan[file] for scan in stream.feeds]  # per scan: the graph's calls
    refs = [scan[file] for scan in stream.outputs]
    names = [o.name for o in pipe.sessions[file].get_outputs()]
    got = [np.asarray(a) for a in ov.run(None, feeds[0][0])]
    why = disagreement(got, refs[0][0], names, ov.precision)
    rival = OPENVINO if ov.precision == "f32" else OPENVINO_BF16
    ms, ratio = paired(
        time_engines({ONNXRUNTIME: pipe.sessions[file], rival: ov}, feeds, refs), rival, ONNXRUNTIME
    )
    if why is not None:
        return {"engine": ONNXRUNTIME, "ms": ms, "ratio": ratio, "reason": why}
    line = f"{rival} / onnxruntime {ratio:.2f} (median over {len(feeds) - 1} scans)"
    if ratio <= 1.0 - MARGIN:
        return {"engine": rival, "ms": ms, "ratio": ratio, "reason": line}
    line += f" (OpenVINO must be {MARGIN:.0%} faster)"
    return {"engine": ONNXRUNTIME, "ms": ms, "ratio": ratio, "reason": line}


def _stays(reason: str) -> dict[str, Any]:
    return {"engine": ONNXRUNTIME, "ms": {}, "reason": reason}


def choose_engines(pipe: Pipeline, threads: dict[str, int | None], precision: str = "f32") -> AutoReport:
    """Pick each graph's engine (module docstring) and put OpenVINO's sessions into
    ``pipe.sessions`` where it won; the caller rebinds the buffers. ``threads``: per graph file;
    ``precision``: OpenVINO's, ``f32`` (``auto``) or ``bf16`` (``auto-bf16``)."""
    from msdnet.runtime.engine.openvino_session import OpenVinoSession

    path, manifest = cache_path(), pipe.artifact.manifest
    keys = {f: cache_key(manifest, f, threads[f], precision) for f in pipe.sessions}
    stored = read_cache(path) if any(k not in _MEMO for k in keys.values()) else {}
    have_ov = openvino_version() is not None
    picks: dict[str, EnginePick] = {}
    new: dict[str, dict[str, Any]] = {}
    stream: StreamInputs | None = None
    for file in list(pipe.sessions):
        entry = _MEMO.get(keys[file]) or stored.get(keys[file])
        cached, ov = entry is not None, None
        if not have_ov:
            entry, cached = _stays("OpenVINO is not installed"), False
        elif entry is None or entry.get("engine") in (OPENVINO, OPENVINO_BF16):
            try:
                ov = OpenVinoSession(pipe.artifact.graphs[file], threads[file], precision)
            except Exception as err:  # noqa: BLE001 - any conversion failure: this graph stays on onnxruntime
                entry, cached = _stays(f"OpenVINO cannot load it: {failure_reason(err)}"), False
        if entry is None:
            stream = stream_inputs(pipe, threads[file]) if stream is None else stream
            try:
                entry = _measure(pipe, file, ov, stream)
            except Exception as err:  # noqa: BLE001 - OpenVINO failing on these inputs: stay
                entry = _stays(f"OpenVINO failed on the graph's inputs: {failure_reason(err)}")
        if not cached and have_ov:
            new[keys[file]] = entry
        _MEMO[keys[file]] = entry
        if entry["engine"] in (OPENVINO, OPENVINO_BF16) and ov is not None:
            pipe.sessions[file] = ov
        ms = {str(k): float(v) for k, v in entry.get("ms", {}).items()}
        ratio = None if entry.get("ratio") is None else float(entry["ratio"])
        picks[file] = EnginePick(file, entry["engine"], ms, str(entry.get("reason", "")), cached, ratio)
    note = "read" if not new else write_cache(path, new)
    return AutoReport(picks, path, note if have_ov else "not used: OpenVINO is not installed")
