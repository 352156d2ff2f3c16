"""``--provider auto``'s time budget: what a first load's measurement may still start.

The budget (``provider_measure.BUDGET_S``) is wall-clock and covers the whole measurement of a
load: OpenVINO's compiles, the reference and warm-up calls and the timed scans. Within it
(``provider_measure.measure``):

- graphs are warmed up one by one, the heads last (usually the costliest), each graph's cost
  taken from its reference call (one call on onnxruntime). A slow graph's engine pick (a call of
  ``WARMUP_ONCE_S`` or more) is *deferred* when its warm-up and one timed scan of every session kept
  so far would end past the budget (after a slow graph with the budget gone, without even its
  reference call): it stays on onnxruntime for this load, is not cached, and a later load measures
  it. The first graph is never deferred, so every load gets further, and neither is the head
  pick (one session per head, on the engines already picked);
- a scan starts only when it is expected (from the last scan) to end within the budget, except that
  at least ``MIN_TIMED_SCANS`` are timed while a scan takes at most ``SLOW_SCAN_S`` and
  ``MIN_SLOW_SCANS`` when it takes longer;
- when the budget will not reach the end of the stream, a session that took at least
  ``CLEARLY_SLOWER`` times the other engine's time on the same graph on each of at least
  ``MIN_TIMED_SCANS`` scans stops being timed: it cannot be picked (the pick goes by the median of
  the paired ratios), and the other sessions get more scans.
"""

from __future__ import annotations

import time

import numpy as np

Label = tuple[str, str]  # (graph file, engine): one timed session

WARMUP_ONCE_S = 0.05  # a first call at least this long is warm-up enough (paper-size heads: 0.2-0.35 s)
MIN_TIMED_SCANS = 3  # scans timed after the warm-up while a scan is cheap, whatever the budget
MIN_SLOW_SCANS = 1  # the same where a scan takes longer than SLOW_SCAN_S
SLOW_SCAN_S = 0.2  # s: a timed scan (inputs and calls) this long is slow: the floor costs at most 0.6 s
CLEARLY_SLOWER = 1.5  # a session this many times slower than the other engine on every scan stops


def fits(deadline: float, seconds: float) -> bool:
    """Work of ``seconds`` started now ends by ``deadline`` (``time.perf_counter``)."""
    return time.perf_counter() + seconds <= deadline


def scan_floor(scan_s: float) -> int:
    """Scans timed whatever the budget, when a scan takes ``scan_s`` seconds."""
    return MIN_TIMED_SCANS if scan_s <= SLOW_SCAN_S else MIN_SLOW_SCANS


def defer(may_wait: bool, deadline: float, planned_s: float, warm_s: float, scan_s: float) -> bool:
    """A graph is deferred (module docstring): it ``may_wait`` (slow, an engine pick, not the
    cheapest), and its warm-up (``warm_s``) and one timed scan of every session kept so far
    (``planned_s``) and of its own (``scan_s``) would not end by ``deadline``."""
    return may_wait and not fits(deadline, warm_s + planned_s + scan_s)


def clearly_slower(ms: dict[Label, list[float]], disagree: dict[Label, str]) -> set[Label]:
    """Sessions to stop timing (module docstring): of a graph's two engines, the one that took at
    least ``CLEARLY_SLOWER`` times the other's time on each of their first ``MIN_TIMED_SCANS`` or
    more scans, where the other may be picked (its outputs agree)."""
    by_file: dict[str, list[Label]] = {}
    for label in ms:
        by_file.setdefault(label[0], []).append(label)
    out: set[Label] = set()
    for labels in by_file.values():
        if len(labels) != 2:
            continue
        a, b = labels
        n = min(len(ms[a]), len(ms[b]))
        if n < MIN_TIMED_SCANS:
            continue
        ratio = np.asarray(ms[a][:n]) / np.asarray(ms[b][:n])
        if np.all(ratio >= CLEARLY_SLOWER) and b not in disagree:
            out.add(a)
        elif np.all(ratio * CLEARLY_SLOWER <= 1.0) and a not in disagree:
            out.add(b)
    return out
