"""``--provider auto``, with a gate in the manifest: the coarse-to-fine head or the dense one.

The coarse-to-fine head (``recon_head_sparse.onnx`` with the manifest's ``gate``) exists to be
faster than the dense head (``recon_head.onnx``), whose values it gives where it computes; on some
engines it is not (OpenVINO compiles the dense head once for its fixed shapes). Both heads are
timed in ``provider_measure.measure``'s stream on the engines their picks gave them, paired by scan;
the pipeline runs the dense head (``Pipeline.gate`` None), the reference the gated head
approximates, when its time over the coarse-to-fine head's, median over the scans, is at most
1 - ``MARGIN``. The pick is cached beside the engine picks, keyed also by both heads' engines.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from msdnet.runtime.model import onnx_spec
from msdnet.runtime.providers.provider_cache import cache_key
from msdnet.runtime.providers.provider_measure import MARGIN, Samples, paired

DENSE, COARSE_TO_FINE = "dense", "coarse-to-fine"
HEADS = (DENSE, COARSE_TO_FINE)
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


def head_key(
    manifest: dict[str, Any], engines: dict[str, str], threads: dict[str, int | None], precision: str
) -> str:
    """The cache key of the head pick: the model, both heads' engines (graph file -> engine),
    the coarse-to-fine head's threads and the machine."""
    on = ", ".join(f"{h} on {engines[f]}" for h, f in FILES.items())
    return cache_key(manifest, f"head: {on}", threads[FILES[COARSE_TO_FINE]], precision)


def head_entry(samples: Samples, engines: dict[str, str]) -> dict[str, Any] | None:
    """The cache record of the head pick from ``samples`` of both heads on ``engines`` (graph file
    -> engine); None when either head has no samples there (its engine failed on the scans)."""
    labels = {h: (f, engines[f]) for h, f in FILES.items()}
    if not all(label in samples.ms for label in labels.values()):
        return None
    calls: dict[str, np.ndarray] = {h: samples.ms[label] for h, label in labels.items()}
    ms, ratio = paired(calls, DENSE, COARSE_TO_FINE)
    n = min(len(v) for v in calls.values())  # a head's engine may have stopped early (provider_budget)
    line = f"dense / coarse-to-fine {ratio:.2f} (median over {n} scans)"
    entry = {"ms": ms, "ratio": ratio, "scans": n}
    if ratio <= 1.0 - MARGIN:
        return entry | {"head": DENSE, "reason": f"{line}: the reference, no gate"}
    return entry | {"head": COARSE_TO_FINE, "reason": f"{line} (the dense head must be {MARGIN:.0%} faster)"}


def pick_of(entry: dict[str, Any], cached: bool) -> HeadPick:
    """The :class:`HeadPick` of a validated cache record."""
    ms = {str(k): float(v) for k, v in entry.get("ms", {}).items()}
    ratio = None if entry.get("ratio") is None else float(entry["ratio"])
    return HeadPick(str(entry["head"]), ms, ratio, str(entry.get("reason", "")), cached)
