"""``--provider auto``: per graph, the faster f32 engine installed here (onnxruntime's CPU
provider or OpenVINO), measured on the model's own kind of scans and cached.

A model's first load measures, within a hard wall-clock ``BUDGET_S`` that covers the compiles
too: seeded radar-like scans, new to every timed session, each graph's calls as the pipeline makes
them, all engines interleaved scan by scan (``provider_measure``; ``provider_budget`` says what
still fits, and a slow graph may be left on onnxruntime, uncached, for a later load). OpenVINO
wins a graph when it is at least ``MARGIN`` faster, paired by scan, and its outputs agree with
onnxruntime's within the export tolerances. With a gate in the manifest the same samples decide
the head (``provider_head``). Picks are cached per model hash,
graph, threads, CPU and library versions (``provider_cache``); an entry that does not validate, or
a cache file that cannot be read or is of another version, counts as absent and is measured again,
with a note. ``docs/latency.md`` has the measurements behind these rules.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from msdnet.runtime.model import onnx_spec

# measure, BUDGET_S and openvino_version are looked up on their modules, where a test patches them
from msdnet.runtime.providers import provider_cache, provider_head, provider_measure
from msdnet.runtime.providers.provider_cache import Cache, cache_key, cache_path, cache_shown, write_cache
from msdnet.runtime.providers.provider_measure import (
    MARGIN,
    ONNXRUNTIME,
    OPENVINO,
    OPENVINO_BF16,
    Label,
    Pipeline,
    Samples,
    failure_reason,
    paired,
)


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
    measured_s: float | None = None  # seconds this load spent measuring; None: every pick cached
    scans: int = 0  # scans timed after the warm-up (0: nothing measured)
    notes: tuple[str, ...] = ()  # why the cache was not used: unreadable file, entries that do not validate
    deferred: tuple[str, ...] = ()  # graphs left for a later load to keep to the budget (provider_budget)

    @property
    def dense_head(self) -> bool:
        """The head pick is the dense head: the pipeline runs it with no gate."""
        return self.head is not None and self.head.head == "dense"

    def summary(self) -> str | None:
        """One line when this load measured (what, how long, where it is cached), else None."""
        if self.measured_s is None:
            return None
        more = f"; {len(self.notes) - 1} more cache notes" if len(self.notes) > 1 else ""
        why = f" ({self.notes[0]}{more})" if self.notes else ""
        later = ""
        if self.deferred:
            budget = f"{provider_measure.BUDGET_S:g} s"
            later = f"; {', '.join(self.deferred)} left on onnxruntime for a later load (budget {budget})"
        return (
            f"provider auto: measured this model's engines here in {self.measured_s:.1f} s over "
            f"{self.scans} scans{why}{later}; picks cached in {cache_shown(self.cache)} ({self.cache_note})"
        )

    def lines(self) -> list[str]:
        head = [] if self.head is None else [f"provider auto: {self.head.line()}"]
        return (
            [f"provider auto: note: {n}" for n in self.notes]
            + [f"provider auto: {p.line()}" for p in self.picks.values()]
            + head
            + [f"provider auto: cache {self.cache} ({self.cache_note})"]
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "picks": {f: p.to_json() for f, p in self.picks.items()},
            "head": None if self.head is None else self.head.to_json(),
            "cache": cache_shown(self.cache),
            "cache_note": self.cache_note,
            "measured_s": self.measured_s,
            "scans": self.scans,
            "notes": list(self.notes),
            "deferred": list(self.deferred),
        }


def _engine_entry(file: str, rival: str, samples: Samples) -> dict[str, Any]:
    """The cache record of ``file``'s pick from ``samples`` (module docstring)."""
    ours, theirs = (file, ONNXRUNTIME), (file, rival)
    if theirs in samples.failed:
        return _stays(f"OpenVINO failed on the graph's inputs: {samples.failed[theirs]}")
    ms, ratio = paired({ONNXRUNTIME: samples.ms[ours], rival: samples.ms[theirs]}, rival, ONNXRUNTIME)
    n = min(len(samples.ms[ours]), len(samples.ms[theirs]))
    entry = {"ms": ms, "ratio": ratio, "scans": n}
    if theirs in samples.disagree:
        return entry | {"engine": ONNXRUNTIME, "reason": samples.disagree[theirs]}
    line = f"{rival} / onnxruntime {ratio:.2f} (median over {over_scans(n, samples.scans)})"
    if ratio <= 1.0 - MARGIN:
        return entry | {"engine": rival, "reason": line}
    return entry | {"engine": ONNXRUNTIME, "reason": f"{line} (OpenVINO must be {MARGIN:.0%} faster)"}


def over_scans(n: int, scans: int) -> str:
    """ "n scans", or where one engine stopped early (``provider_budget``), "n of the scans scans"."""
    return f"{n} scans" if n == scans else f"{n} of {scans} scans: the slower engine stopped early"


def _stays(reason: str) -> dict[str, Any]:
    return {"engine": ONNXRUNTIME, "ms": {}, "reason": reason}


def _later(budget_s: float) -> dict[str, Any]:
    """The pick of a graph deferred to keep to the budget (``provider_budget``); never cached."""
    return _stays(
        f"not measured within the {budget_s:g} s budget: onnxruntime until a later load measures it"
    )


def choose_engines(pipe: Pipeline, threads: dict[str, int | None], precision: str = "f32") -> AutoReport:
    """Pick each graph's engine and, with a gate in the manifest, the head (module docstring), from
    the cache or measured (then cached); put OpenVINO's sessions into ``pipe.sessions`` where it
    won. The caller rebinds the buffers and applies the head pick (``AutoReport.dense_head``).
    ``threads``: per graph file; ``precision``: OpenVINO's, ``f32`` (``auto``) or ``bf16``
    (``auto-bf16``)."""
    from msdnet.runtime.providers.openvino_session import OpenVinoSession

    start = time.perf_counter()
    path, manifest = cache_path(), pipe.artifact.manifest
    if provider_cache.openvino_version() is None:
        picks = {f: EnginePick(f, ONNXRUNTIME, reason="OpenVINO is not installed") for f in pipe.sessions}
        return AutoReport(picks, path, "not used: OpenVINO is not installed")
    rival = OPENVINO if precision == "f32" else OPENVINO_BF16
    keys = {f: cache_key(manifest, f, threads[f], precision) for f in pipe.sessions}
    cache = Cache(path)
    entries = {f: cache.get(keys[f], "engine", (ONNXRUNTIME, rival), f) for f in pipe.sessions}
    cached = {f: e is not None for f, e in entries.items()}
    voxelizer = provider_measure.warm_voxelizer(pipe) if not all(cached.values()) else None
    ov: dict[str, Any] = {}
    for f, entry in entries.items():
        if entry is None or entry["engine"] == rival:
            try:
                ov[f] = OpenVinoSession(pipe.artifact.graphs[f], threads[f], precision)
            except Exception as err:  # noqa: BLE001 - any conversion failure: this graph stays on onnxruntime
                entries[f], cached[f] = _stays(f"OpenVINO cannot load it: {failure_reason(err)}"), False
    timed = [f for f, e in entries.items() if e is None]
    runs: dict[Label, Any] = {}
    for f in timed:
        runs |= {(f, ONNXRUNTIME): pipe.sessions[f], (f, rival): ov[f]}
    head_files = list(provider_head.FILES.values())
    contest = pipe.artifact.gate is not None and all(f in pipe.sessions for f in head_files)
    head_entry, head_cached = None, False
    if contest and not any(f in timed for f in head_files):
        key = provider_head.head_key(
            manifest, {f: entries[f]["engine"] for f in head_files}, threads, precision
        )
        head_entry = cache.get(key, "head", provider_head.HEADS, "the head pick")
        head_cached = head_entry is not None
    for f in head_files if contest and head_entry is None else []:
        if f not in timed:  # its engine is known: time it there for the head pick
            engine = entries[f]["engine"]
            runs[(f, engine)] = ov[f] if engine == rival else pipe.sessions[f]
    if voxelizer is not None:
        voxelizer.join()
    samples, deferred = None, ()
    if runs:
        deadline = start + provider_measure.BUDGET_S  # hard: compiles, warm-ups and scans
        samples = provider_measure.measure(pipe, runs, threads[onnx_spec.ENCODER.file], deadline)
        deferred = samples.deferred
        for f in timed:
            entries[f] = (
                _later(provider_measure.BUDGET_S) if f in deferred else _engine_entry(f, rival, samples)
            )
    new = {keys[f]: e for f, e in entries.items() if not cached[f] and f not in deferred}
    head = None
    if contest:
        picked = {f: entries[f]["engine"] for f in head_files}
        key = provider_head.head_key(manifest, picked, threads, precision)
        if head_entry is None and samples is not None:
            head_entry = provider_head.head_entry(samples, picked)
            if head_entry is not None:
                new[key] = head_entry
        if head_entry is not None:
            head = provider_head.pick_of(head_entry, head_cached)
            cache.keep(key, head_entry)
    picks: dict[str, EnginePick] = {}
    for f, entry in entries.items():
        if f not in deferred:  # a deferred graph is measured by the next load, in this process too
            cache.keep(keys[f], entry)
        if entry["engine"] == rival and f in ov:
            pipe.sessions[f] = ov[f]
        ms = {str(k): float(v) for k, v in entry.get("ms", {}).items()}
        ratio = None if entry.get("ratio") is None else float(entry["ratio"])
        picks[f] = EnginePick(f, entry["engine"], ms, str(entry.get("reason", "")), cached[f], ratio)
    note = write_cache(path, new) if new else "read"
    spent = time.perf_counter() - start if new or samples is not None else None
    scans = samples.scans if samples is not None else 0
    return AutoReport(picks, path, note, head, spent, scans, tuple(cache.notes), deferred)
