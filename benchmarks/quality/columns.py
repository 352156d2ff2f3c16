"""Column keys and colours shared by the quality suite (``suite``) and its writers (``report``).

Kept apart so that ``suite`` and ``report`` do not import each other.
"""

from __future__ import annotations

from msdnet.runtime.metrics.cloud import FSCORE_THRESHOLDS

FSCORE_KEYS = tuple(f"fscore@{t:g}" for t in FSCORE_THRESHOLDS)  # "fscore@0.05", ...
PANEL_COLOURS = {"radar": "tab:red", "r2ldm": "tab:orange", "msdnet": "tab:blue", "lidar": "0.25"}
