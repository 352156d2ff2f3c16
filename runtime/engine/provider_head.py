"""``--provider auto``, once each graph has its engine: the coarse-to-fine head or the dense one.

The coarse-to-fine head (``recon_head_sparse.onnx`` with the manifest's ``gate``) is there to be
faster than the dense head (``recon_head.onnx``). Where it computes it gives the dense head's
values, and its gate (``export.gate``) keeps a calibrated share of the dense head's points. It
is faster only on some engines. OpenVINO compiles the dense head once, because its shapes never
change, and in bfloat16 its 3x3x3 convolutions are quick; the coarse-to-fine head's shapes
change every frame. Measured on ``astyx-lite`` with ``auto-bf16`` (dense head on OpenVINO bf16,
coarse-to-fine head on onnxruntime): on all 440 Astyx frames in order, interleaved, frames took
0.93–0.96 of the time they took with the coarse-to-fine head, and decoded 5,442 points against
5,392 (``docs/results/latency-thirteenth``).

So when the manifest has a gate, both heads are timed on the sessions their picks gave them.
They run on a second stream of ``STREAM_SCANS`` seeded scans (seeds from ``HEAD_SEED``), new to
every session, since the engine picks' own stream has warmed some of them. The heads are
interleaved and paired by scan, as the engine picks are. The pipeline runs the dense head
(``Pipeline.gate`` None) when its time over the coarse-to-fine head's, median over the scans, is
at most 1 - ``MARGIN``. Its outputs are then the dense reference's: every point the gated head
decodes, and the few the gate leaves out. The pick is cached beside the engine picks, keyed
also by both heads' engines. Without OpenVINO, ``auto`` is ``cpu`` and there is no contest.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

from msdnet.runtime.engine import provider_auto
from msdnet.runtime.engine.provider_auto import MARGIN, EnginePick, cache_key
from msdnet.runtime.model import onnx_spec

Pipeline = Any  # runtime.engine.pipeline.Pipeline (which imports this module)

HEAD_SEED = 1000  # first seed of the heads' stream: apart from the engine picks' (0 to STREAM_SCANS - 1)
DENSE, COARSE_TO_FINE = "dense", "coarse-to-fine"
FILES = {DENSE: onnx_spec.RECON_HEAD.file, COARSE_TO_FINE: onnx_spec.RECON_HEAD_SPARSE.file}


@dataclass(frozen=True)
class HeadPick:
    """The head graph ``auto`` runs, and why."""

    head: str  # DENSE or COARSE_TO_FINE
    ms: dict[str, float] = field(default_factory=dict)  # median ms a scan by head, on their engines
    ratio: float | None = None  # dense / coarse-to-fine, median over the scans
    reason: str = ""  # one line: the comparison
    cached: bool = False  # taken from the cache (measured by an earlier load)

    def line(self) -> str:
        times = ", ".join(f"{h} {v:.3f} ms" for h, v in self.ms.items())
        source = "cached" if self.cached else "measured"
        return f"head: {self.head} ({times + '; ' if times else ''}{self.reason}; {source})"

    def to_json(self) -> dict[str, Any]:
        out = {"head": self.head, "ms": dict(self.ms), "ratio": self.ratio}
        return out | {"reason": self.reason, "cached": self.cached}


def head_key(pipe: Pipeline, picks: dict[str, EnginePick], threads: int | None, precision: str) -> str:
    """The cache key of the head pick: the model, both heads' engines, threads and machine."""
    engines = ", ".join(f"{h} on {picks[f].engine}" for h, f in FILES.items())
    return cache_key(pipe.artifact.manifest, f"head: {engines}", threads, precision)


def measure_heads(pipe: Pipeline, threads: int | None) -> dict[str, Any]:
    """Time both heads on ``pipe.sessions`` over the heads' stream (module docstring); -> the
    cache entry: {"head", "ms", "ratio", "reason"}."""
    stream = provider_auto.stream_inputs(pipe, threads, HEAD_SEED)
    sessions = {h: pipe.sessions[f] for h, f in FILES.items()}
    feeds = {h: [scan[f] for scan in stream.feeds] for h, f in FILES.items()}
    refs = {h: [scan[f] for scan in stream.outputs] for h, f in FILES.items()}
    calls = provider_auto.time_engines(sessions, feeds, refs)  # ms a scan, (STREAM_SCANS - 1,) per head
    ms, ratio = provider_auto.paired(calls, DENSE, COARSE_TO_FINE)
    line = f"dense / coarse-to-fine {ratio:.2f} (median over {len(stream.feeds) - 1} scans)"
    if ratio <= 1.0 - MARGIN:
        return {"head": DENSE, "ms": ms, "ratio": ratio, "reason": f"{line}: the reference, no gate"}
    line += f" (the dense head must be {MARGIN:.0%} faster)"
    return {"head": COARSE_TO_FINE, "ms": ms, "ratio": ratio, "reason": line}


def choose_head(
    pipe: Pipeline, report: provider_auto.AutoReport, threads: dict[str, int | None], precision: str
) -> provider_auto.AutoReport:
    """``report`` (the engine picks, whose sessions ``pipe.sessions`` holds) with the head pick of
    the module docstring, from the cache or measured (then cached); unchanged when the manifest has
    no gate or OpenVINO is not installed. The caller applies it (``Pipeline.gate``)."""
    if pipe.artifact.gate is None or provider_auto.openvino_version() is None:
        return report
    if not all(f in pipe.sessions for f in FILES.values()):
        return report
    key = head_key(pipe, report.picks, threads[FILES[COARSE_TO_FINE]], precision)
    entry = provider_auto._MEMO.get(key) or provider_auto.read_cache(report.cache).get(key)
    cached, note = entry is not None, report.cache_note
    if entry is None:
        entry = measure_heads(pipe, threads[FILES[COARSE_TO_FINE]])
        written = provider_auto.write_cache(report.cache, {key: entry})
        note = written if note == "read" else note
    provider_auto._MEMO[key] = entry
    ms = {str(k): float(v) for k, v in entry.get("ms", {}).items()}
    ratio = None if entry.get("ratio") is None else float(entry["ratio"])
    pick = HeadPick(str(entry["head"]), ms, ratio, str(entry.get("reason", "")), cached)
    return replace(report, head=pick, cache_note=note)
