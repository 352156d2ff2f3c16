"""``msdnet-bench quality --metrics official|both``: the R2LDM authors' formulas beside ours.

The formulas and the per-method accumulator (:class:`OfficialFrames`) live in
``msdnet.runtime.metrics.official``; this module sets their summaries beside ours: margins of
MSDNet against EVERY R2LDM row, in both metric sets, beside the margins the MSDNet paper reports
over R2LDM, as results.json blocks and markdown.
"""

from __future__ import annotations

import math
from typing import Any

from msdnet.benchmarks.eval_methods import Method, primary
from msdnet.runtime.metrics.official import OfficialFrames

# MSDNet's margins over R2LDM in its paper (percent; negative: lower is better), per metric key of
# ours and of the official set (the paper's "MHD" is what the script computes as squared Hausdorff)
PAPER_MARGINS = {"CD": -15.0, "MHD": -66.0, "F-score": 44.0, "JSD": -30.0}
OURS_KEYS = {"CD": "cd", "MHD": "mhd", "F-score": "fscore@0.05", "JSD": "jsd"}
OFFICIAL_KEYS = {"CD": "chamfer_squared_l2", "MHD": "hausdorff_squared_l2", "F-score": "fscore", "JSD": "jsd"}


def _pct(a: float, b: float) -> float:
    ok = math.isfinite(a) and math.isfinite(b) and b != 0
    return 100.0 * (a - b) / abs(b) if ok else float("nan")


def margins_each(
    summary: dict[str, dict[str, float]], methods: list[Method], keys: dict[str, str]
) -> list[dict[str, Any]]:
    """MSDNet (the primary row) against every R2LDM row: per metric of ``keys`` (paper name -> our
    summary key) the values, ``percent`` = 100 (MSDNet - R2LDM) / R2LDM and the paper's margin."""
    ms = primary(methods, "msdnet")
    if ms is None:
        return []
    out = []
    for r2 in (m for m in methods if m.role == "r2ldm"):
        rows = {}
        for label, key in keys.items():
            a, b = summary[ms.name][key], summary[r2.name][key]
            rows[label] = {
                "key": key,
                "msdnet": a,
                "r2ldm": b,
                "percent": _pct(a, b),
                "paper": PAPER_MARGINS[label],
            }
        out.append({"msdnet": ms.name, "r2ldm": r2.name, "metrics": rows})
    return out


def official_section(
    frames: dict[str, OfficialFrames], summary: dict[str, dict[str, float]], methods: list[Method]
) -> dict[str, Any]:
    """results.json's ``official`` block: summaries per method, margins in both metric sets."""
    off = {name: f.summary() for name, f in frames.items()}
    return {
        "preprocessing": "0.125 m voxel centroids in [-16, 16] x [-16, 16] x [-0.5, 4.5] m (half-open)",
        "summary": off,
        "margins": margins_each(off, methods, OFFICIAL_KEYS),
        "margins_ours": margins_each(summary, methods, OURS_KEYS),
    }


def _f(x: float, digits: int = 3) -> str:
    return "–" if not math.isfinite(x) else f"{x:.{digits}f}"


def _margin_lines(title: str, blocks: list[dict[str, Any]]) -> list[str]:
    out = []
    for b in blocks:
        out += ["", f"{title}: {b['msdnet']} vs {b['r2ldm']}", ""]
        out += ["| metric | MSDNet | R2LDM | change | paper |", "|---|---:|---:|---:|---:|"]
        for label, r in b["metrics"].items():
            vals = f"{_f(r['msdnet'], 4)} | {_f(r['r2ldm'], 4)} | {_f(r['percent'], 1)} %"
            out.append(f"| {label} ({r['key']}) | {vals} | {r['paper']:+.0f} % |")
    return out


def official_markdown(doc: dict[str, Any]) -> list[str]:
    """Markdown lines of the official table and of the margins over every R2LDM row."""
    sec = doc["official"]
    out = ["", "## The R2LDM authors' formulas (eval_metric_2025.py)", ""]
    out += [f"Both clouds preprocessed: {sec['preprocessing']}; frames with an empty side skipped.", ""]
    out += [
        "| Method | CD² sum (m²) | Hausdorff² (m²) | F@0.05 m | precision | recall | JSD (distance) "
        "| MMD | points / frame | frames (skipped) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for m in doc["methods"]:
        s = sec["summary"][m["name"]]
        vals = [s["chamfer_squared_l2"], s["hausdorff_squared_l2"], s["fscore"], s["precision"], s["recall"]]
        cells = " | ".join(_f(v, 4) for v in vals)
        frames = f"{int(s['pairs_evaluated'])} ({int(s['pairs_skipped_empty'])})"
        out.append(
            f"| {m['name']} | {cells} | {_f(s['jsd'], 4)} | {_f(s['mmd'], 4)} | "
            f"{_f(s['generated_points'], 0)} | {frames} |"
        )
    out += _margin_lines("Margins, official formulas", sec["margins"])
    out += _margin_lines("Margins, our formulas", sec["margins_ours"])
    return out
