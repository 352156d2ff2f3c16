"""Outputs of the evaluation commands: results.json, results.md and BEV picture strips.

Everything is written atomically (``runtime.io.atomic.atomic_output``: a temporary file in the same
folder, then ``os.replace``). Non-finite numbers become JSON ``null`` so results.json stays
strict JSON; numpy scalars become plain numbers.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from msdnet.benchmarks.quality.columns import FSCORE_KEYS
from msdnet.runtime.io.atomic import atomic_output
from msdnet.runtime.io.pictures import COUNTS_KEY, draw_grid
from msdnet.runtime.spec.grid import GridConfig

# MSDNet paper, Table I (VoD) as printed: CD (unit not stated), MHD (printed x1e-2, here in m),
# F-score (threshold not stated), JSD, MMD (printed x1e-4, here as is).
PAPER_TABLE1_VOD = {
    "R2LDM": {"cd": 6.07, "mhd": 1.7228, "fscore": 0.27, "jsd": 0.35, "mmd": 21.88e-4},
    "MSDNet": {"cd": 5.16, "mhd": 0.5898, "fscore": 0.39, "jsd": 0.21, "mmd": 5.51e-4},
}
# MSDNet paper, Table II (ablations on VoD): CD, MHD (m), JSD, MMD
PAPER_TABLE2 = {
    "w/o RGFD": {"cd": 5.88, "mhd": 0.6643, "jsd": 0.22, "mmd": 5.94e-4},
    "w/o DGFD": {"cd": 9.29, "mhd": 1.3557, "jsd": 0.27, "mmd": 12.03e-4},
    "w/o Noise Adapter": {"cd": 5.53, "mhd": 0.6174, "jsd": 0.22, "mmd": 6.21e-4},
    "MSDNet (Full)": {"cd": 5.16, "mhd": 0.5898, "jsd": 0.21, "mmd": 5.51e-4},
}
PAPER_NOTE = (
    "Paper numbers are quoted for context only: the paper does not state the CD variant or unit, "
    "the F-score threshold, or the JSD/MMD histogram settings, and it trains on the full VoD set; "
    "compare the margins (MSDNet vs R2LDM), not the absolute values."
)


def to_jsonable(obj: Any) -> Any:
    """Recursively: non-finite floats -> None, numpy scalars/arrays -> Python, tuples -> lists."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: Path, doc: dict[str, Any]) -> Path:
    """Write ``doc`` as strict, indented JSON, atomically."""
    text = json.dumps(to_jsonable(doc), indent=1, allow_nan=False) + "\n"
    return write_text(path, text)


def write_text(path: Path, text: str) -> Path:
    """Write UTF-8 text atomically."""
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def fmt(x: Any, digits: int = 3, scale: float = 1.0) -> str:
    """A table cell: ``x * scale`` with ``digits`` decimals; "–" for None / nan; "yes"/"no"."""
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    v = float(x) * scale
    return f"{v:.{digits}f}" if math.isfinite(v) else "–"


def metric_label(key: str) -> str:
    """The name of a metric key in tables: ``fscore@0.1`` -> "F@0.1 m (↑)", ``cd`` -> "CD (m) (↓)"."""
    if key.startswith("fscore@"):
        return f"F@{key.split('@')[1]} m (↑)"
    labels = {"cd": "CD (m)", "cd_squared": "CD² (m²)", "mhd": "MHD (m)", "jsd": "JSD", "mmd": "MMD"}
    return f"{labels.get(key, key)} (↓)"


def md_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """Markdown table lines (first column left-aligned, the rest right-aligned)."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" + "---:|" * (len(headers) - 1)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def _quality_rows(doc: dict[str, Any]) -> list[list[str]]:
    rows = []
    for m in doc["methods"]:
        s = doc["summary"][m["name"]]
        rows.append(
            [m["name"], fmt(s["cd"]), fmt(s["cd_squared"]), fmt(s["mhd"])]
            + [fmt(s[k]) for k in FSCORE_KEYS]
            + [
                fmt(s["jsd"]),
                fmt(s["mmd"], 2, 1e4),
                fmt(s["points"], 0),
                f"{s['frames']} ({s['empty_frames']})",
            ]
        )
    return rows


def quality_markdown(doc: dict[str, Any]) -> str:
    """results.md of ``msdnet-bench quality`` (``doc`` is results.json's content)."""
    ev = doc["evaluation"]
    out = [
        f"# Point-cloud quality: {ev['dataset']} / {ev['split']}, {ev['frames']} frames",
        "",
        f"Reference: {ev['reference']}. Every cloud is cropped like the reference (grid box "
        f"{ev['grid']['point_range']} m, ±{ev['grid']['fov_deg']:g}° field of view); radar frame. "
        f"Seed {ev['seed']}. Machine: {doc['machine']['cpu']} ({doc['machine']['logical_cores']} cores).",
        "",
        "## Every method: scene metrics, mean over frames",
        "",
    ]
    heads = ["Method", "CD (m)", "CD² (m²)", "MHD (m)"] + [f"F@{k.split('@')[1]} m" for k in FSCORE_KEYS]
    heads += ["JSD", "MMD (×10⁻⁴)", "points / frame", "frames (empty)"]
    out += md_table(heads, _quality_rows(doc))
    out += ["", "CD is the mean of both directed mean nearest-neighbour distances; means skip frames "]
    out[-1] += "where a metric is undefined (an empty prediction)."
    ablations = [m for m in doc["methods"] if m["role"] == "ablation"]
    if ablations and doc.get("margins"):
        full = doc["margins"]["msdnet"]
        out += ["", "## Ablations: scene metrics, mean over frames", ""]
        rows = []
        for name in [m["name"] for m in ablations] + [full]:
            s = doc["summary"][name]
            rows.append([name, fmt(s["cd"]), fmt(s["mhd"]), fmt(s["jsd"]), fmt(s["mmd"], 2, 1e4)])
        out += md_table(["Method", "CD (m)", "MHD (m)", "JSD", "MMD (×10⁻⁴)"], rows)
    if doc.get("agreement"):
        out += ["", "## torch vs onnxruntime (same weights, same noise)", ""]
        rows = [
            [a["torch"], a["onnxruntime"], fmt(100 * a["max_relative_difference"], 3) + " %", fmt(a["ok"])]
            for a in doc["agreement"]
        ]
        out += md_table(["torch", "onnxruntime", "largest relative difference", "within 1 %"], rows)
    if doc.get("margins"):
        mg = doc["margins"]
        out += ["", f"## Margins: {mg['msdnet']} vs {mg['r2ldm']}", ""]
        rows = []
        for k, r in mg["metrics"].items():
            bar = "–" if r["bar"] is None else f"{r['bar']:+.0f} %"
            vals = [fmt(doc["summary"][mg[w]][k], 4) for w in ("msdnet", "r2ldm")]
            rows.append([metric_label(k), *vals, fmt(r["percent"], 1) + " %", bar, fmt(r["met"])])
        out += md_table(["metric", "MSDNet", "R2LDM", "change", "bar", "met"], rows)
    out += ["", "## Paper context (MSDNet, VoD)", ""]
    rows = [
        [n, fmt(v["cd"], 2), fmt(v["mhd"], 4), fmt(v["fscore"], 2), fmt(v["jsd"], 2), fmt(v["mmd"], 2, 1e4)]
        for n, v in PAPER_TABLE1_VOD.items()
    ]
    out += ["Every method (the paper's Table I):", ""] + md_table(
        ["Method", "CD", "MHD (m)", "F-score", "JSD", "MMD (×10⁻⁴)"], rows
    )
    rows = [
        [n, fmt(v["cd"], 2), fmt(v["mhd"], 4), fmt(v["jsd"], 2), fmt(v["mmd"], 2, 1e4)]
        for n, v in PAPER_TABLE2.items()
    ]
    out += ["", "Ablations (the paper's Table II):", ""] + md_table(
        ["Method", "CD", "MHD (m)", "JSD", "MMD (×10⁻⁴)"], rows
    )
    out += ["", "Paper margins MSDNet vs R2LDM: CD −15.0 %, MHD −65.8 %, F-score +44.4 %.", "", PAPER_NOTE]
    if doc.get("objects"):
        out += ["", *objects_markdown(doc)]
    if doc.get("pictures"):
        out += ["", "## Pictures (BEV: radar | R2LDM | MSDNet | LiDAR; scored objects boxed)", ""]
        out += [f"![frame {fid}]({path})" for fid, path in doc["pictures"].items()]
    return "\n".join(out) + "\n"


def objects_markdown(doc: dict[str, Any]) -> list[str]:
    """The "Objects" section of results.md: every method over all scored objects, then hit@5 /
    object CD per class and per range band (``doc["objects"]``, ``benchmarks.quality.objects``)."""
    obj = doc["objects"]
    d = obj["definition"]
    summary = obj["summary"]
    names = [m["name"] for m in doc["methods"] if m["name"] in summary]
    out = [
        "## Objects (labelled 3D boxes the LiDAR sees)",
        "",
        f"An object is scored when its box centre lies in the crop and the reference holds at least "
        f"{d['min_lidar_points']} points in the box grown by {d['grow_m']:g} m; hit@{d['hit_points']}: share "
        f"of objects with at least {d['hit_points']} of the method's points in the grown box; object CD over "
        f"the objects hit; radar kept: share of the radar points within {d['keep_radius_m']:g} m of the "
        f"LiDAR with a point of the method's cloud within {d['keep_radius_m']:g} m (pooled over frames).",
        "",
    ]
    rows = []
    for n in names:
        o, k = summary[n]["overall"], summary[n]["radar_kept"]
        rows.append(
            [n, fmt(o["objects"]), fmt(o["hit@5"]), fmt(o["object_cd"]), fmt(o["points"], 1)]
            + [fmt(o["lidar_points"], 1), fmt(k["share"]), f"{k['kept']} / {k['near']}"]
        )
    heads = ["Method", "objects", "hit@5 (↑)", "object CD (m) (↓)", "points / object"]
    heads += ["LiDAR points / object", "radar kept (↑)", "kept / near"]
    out += md_table(heads, rows)
    for group, title in (("by_class", "class"), ("by_range", "range band")):
        keys: list[str] = []
        for n in names:
            keys += [g for g in summary[n][group] if g not in keys]
        out += ["", f"Per {title}: hit@5 / object CD (m) (objects)", ""]
        rows = []
        for n in names:
            cells = []
            for g in keys:
                r = summary[n][group].get(g)
                empty = r is None or not r["objects"]
                cells.append("–" if empty else f"{fmt(r['hit@5'])} / {fmt(r['object_cd'])}")
            rows.append([n, *cells])
        first = summary[names[0]][group] if names else {}
        counts = [f"{g} ({first[g]['objects'] if g in first else 0})" for g in keys]
        out += md_table(["Method", *counts], rows)
    return out


def picture_strip(
    path: Path,
    panels: Sequence[tuple[str, np.ndarray, str]],
    grid: GridConfig,
    title: str = "",
    dpi: int = 100,
    boxes: Sequence[np.ndarray] = (),
) -> Path:
    """One PNG with a BEV panel per (label, points (N, >=2) [x, y, ...] radar frame, colour).

    As ``runtime.io.pictures.render_bev``: x forward drawn upward, y left drawn to the left, the grid box
    and the field of view outlined; ``boxes``: (4, 2) [x, y] footprints drawn on every panel. Each
    panel's title counts its points, the points scored for that frame (``per_frame`` ``points`` of
    results.json), and the PNG keeps those counts (``pictures.read_counts``).
    Written atomically; returns the path.
    """
    fig = Figure(figsize=(4 * len(panels), 4.6), dpi=dpi)
    FigureCanvasAgg(fig)
    counts: dict[str, int] = {}
    for i, (label, pts, colour) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        p = np.asarray(pts)
        ax.scatter(p[:, 1], p[:, 0], s=1.0 if len(p) > 2000 else 3.0, c=colour, linewidths=0)
        draw_grid(ax, grid, lw=0.9, margin=0.03)
        for corners in boxes:
            ring = np.vstack([corners, corners[:1]])
            ax.plot(ring[:, 1], ring[:, 0], color="tab:green", lw=0.8)
        ax.set_xlabel("y (m, left)", fontsize=8)
        ax.set_aspect("equal", adjustable="box")
        ax.set_title(f"{label} ({len(p):,})", fontsize=9)
        counts[label] = len(p)
        if i == 0:
            ax.set_ylabel("x (m, forward)", fontsize=8)
        ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", metadata={COUNTS_KEY: json.dumps(counts)})
    return Path(path)
