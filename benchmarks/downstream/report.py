"""results.md of the downstream benchmarks (``msdnet-bench odometry`` and ``msdnet-bench place``),
with the MSDNet paper's Tables V and VI beside them for context."""

from __future__ import annotations

from typing import Any

from msdnet.benchmarks.quality.report import fmt, md_table

# MSDNet paper, Table V (VoD odometry, mean over sequences 03/04/22): t_rel, r_rel as printed
PAPER_TABLE5_MEAN = {"R2LDM": (0.56, 0.66), "MSDNet": (0.24, 0.46)}
# MSDNet paper, Table VI (in-house place recognition): Recall@1/3/5 in percent
PAPER_TABLE6 = {
    "4D radar": (47.06, 64.14, 71.16),
    "R2LDM": (50.89, 65.13, 70.80),
    "MSDNet": (58.54, 67.68, 72.71),
}


def _sequence_line(doc: dict[str, Any]) -> str:
    ev = doc["evaluation"]
    seqs = ", ".join(
        f"{s['index']} ({s['frames']} frames{', loop' if s['has_loop'] else ''})" for s in ev["sequences"]
    )
    return f"Data: {ev['data']}; sequences {seqs}. Seed {ev['seed']}. Clouds: {ev['clouds']}."


def odometry_markdown(doc: dict[str, Any]) -> str:
    """results.md of ``msdnet-bench odometry``."""
    out = ["# GICP odometry (small_gicp, scan to scan)", "", _sequence_line(doc), ""]
    rows = []
    for m in doc["methods"]:
        r = doc["results"][m["name"]]["overall"]
        rows.append(
            [
                m["name"],
                fmt(r["translation_m"], 4),
                fmt(r["rotation_deg"], 4),
                fmt(r["translation_pct"], 2),
                fmt(r["pairs"]),
            ]
        )
    heads = ["Method", "t_rel (m / frame)", "r_rel (° / frame)", "t_rel (% of distance)", "frame pairs"]
    out += md_table(heads, rows)
    out += ["", "Per sequence, t_rel (m / frame) / r_rel (° / frame):", ""]
    seq_ids = [str(s["index"]) for s in doc["evaluation"]["sequences"]]
    rows = []
    for m in doc["methods"]:
        per = doc["results"][m["name"]]["sequences"]
        rows.append(
            [m["name"]]
            + [f"{fmt(per[i]['translation_m'], 4)} / {fmt(per[i]['rotation_deg'], 4)}" for i in seq_ids]
        )
    out += md_table(["Method"] + [f"seq {i}" for i in seq_ids], rows)
    out += [
        "",
        "Paper context (MSDNet Table V, VoD, mean of sequences 03/04/22; units as printed there):",
        "",
    ]
    out += md_table(
        ["Method", "t_rel", "r_rel"], [[n, fmt(t, 2), fmt(r, 2)] for n, (t, r) in PAPER_TABLE5_MEAN.items()]
    )
    return "\n".join(out) + "\n"


def place_markdown(doc: dict[str, Any]) -> str:
    """results.md of ``msdnet-bench place``."""
    ev = doc["evaluation"]
    ks = [str(k) for k in ev["ks"]]
    out = ["# ScanContext place recognition", "", _sequence_line(doc), ""]
    out += [
        f"A query is a frame with a true match (within {ev['revisit_radius']:g} m) among the frames "
        f"more than {ev['exclude_recent']} frames before it; queries without one are skipped.",
        "",
    ]
    rows = []
    for m in doc["methods"]:
        r = doc["results"][m["name"]]["overall"]
        rows.append([m["name"]] + [fmt(r["recall"][k], 1, 100.0) for k in ks] + [fmt(r["queries"])])
    out += md_table(["Method"] + [f"Recall@{k} (%)" for k in ks] + ["queries"], rows)
    if all(doc["results"][m["name"]]["overall"]["queries"] == 0 for m in doc["methods"]):
        out += ["", "No query had a true match: simulate longer sequences with loops (closures need "]
        out[-1] += "150 frames), or lower --exclude-recent."
    out += ["", "Paper context (MSDNet Table VI, in-house dataset, %):", ""]
    rows = [[n] + [fmt(v, 2) for v in vals] for n, vals in PAPER_TABLE6.items()]
    out += md_table(["Method", "Recall@1", "Recall@3", "Recall@5"], rows)
    return "\n".join(out) + "\n"
