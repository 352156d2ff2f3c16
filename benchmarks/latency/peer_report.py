"""results.md sections of ``msdnet-bench latency`` for the coarse-to-fine head and the peer engines,
and the goal rows (head, peers, per-frame budgets)."""

from __future__ import annotations

import math
from typing import Any

OTHER_HEAD = "recon_head_other"  # peers' stage: the head graph ours does not run (peers.peer_specs)

ENGINE_LABELS = {
    "onnxruntime": "onnxruntime (ours)",
    "openvino": "OpenVINO",
    "openvino_bf16": "OpenVINO bf16",
    "torch_eager": "torch eager",
    "torch_compile": "torch.compile",
}
STAGE_NAMES = {
    "encoder": "encoder",
    "rgfd_adapter": "RGFD + adapter",
    "ddim_loop": "DDIM loop",
    "recon_head": "head",
}
PAPER_PRESET_S = 0.6 * 0.384  # goal: 0.6 x the paper preset's 0.384 s with the dense head
LITE_T50_MS = 45.0  # goal: the lite model at T_m = 50
OLD_GRAPHS_SHARE = 0.35  # goal: paper-width total <= 0.35 x its unoptimised graphs, same run


def goal_rows(res: dict[str, Any]) -> list[tuple[str, float, str, float]]:
    """(goal, measured, op, target) rows this module adds to the goals table."""
    r, total = res["ratios"], res["stages_ms"]["total"]["median"]
    rows = [
        ("coarse-to-fine head / dense head", r.get("head_over_dense_head", math.nan), "<=", 0.25),
        (
            "coarse-to-fine head / dense head, on a stream",
            r.get("head_over_dense_head_stream", math.nan),
            "<=",
            0.25,
        ),
        ("our engine / best peer, graph stages total", r.get("engine_over_best_peer", math.nan), "<=", 0.8),
        (
            "our engine / best f32 peer, graph stages total",
            r.get("engine_over_best_f32_peer", math.nan),
            "<=",
            0.8,
        ),
    ]
    old = res.get("against_old", {})
    if "new_over_old" in old:
        rows.append(("total / the old graphs' total, same run", old["new_over_old"], "<=", OLD_GRAPHS_SHARE))
    if res["preset"] == "paper":
        rows.append(
            ("paper preset, s per frame (0.6 x 0.384 s)", total / 1e3, "<=", round(PAPER_PRESET_S, 4))
        )
    if res["preset"] == "lite" and res["models"]["msdnet"]["steps"] == 50:
        rows.append(("lite preset at T_m = 50, ms per frame", total, "<=", LITE_T50_MS))
    return rows


def _fmt(v: Any, nd: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{nd}f}" if isinstance(v, float) else str(v)


def head_section(res: dict[str, Any]) -> list[str]:
    """The coarse-to-fine head against the dense head, same run and input."""
    h = res.get("head", {})
    if "sparse" not in h:
        return ["", "## Coarse-to-fine head", "", h.get("note", "not measured")]
    out = [
        "",
        "## Coarse-to-fine head vs the dense head (same input, alternating calls)",
        "",
        f"Gate: {h['gate_note']}. Half-scale voxels decoded at full scale: {h['head_voxels']} of "
        f"{h['half_voxels']} ({h['head_voxels'] / max(1, h['half_voxels']):.1%}).",
        "",
        "| head | median ms | p90 | min | decoded points |",
        "|---|---:|---:|---:|---:|",
        f"| coarse-to-fine (recon_head_sparse.onnx) | {_fmt(h['sparse']['median'])} | "
        f"{_fmt(h['sparse']['p90'])} | {_fmt(h['sparse']['min'])} | {h['points_sparse']} |",
        f"| dense (recon_head.onnx, reference) | {_fmt(h['dense']['median'])} | {_fmt(h['dense']['p90'])} | "
        f"{_fmt(h['dense']['min'])} | {h['points_dense']} |",
        "",
        f"Ratio {_fmt(h['head_over_dense_head'], 3)}; points lost to the gate {h['points_lost_share']:.2%}. "
        f"With this input's keep-every-point gate ({h['keep_all_gate']:.4g}) the decoded points "
        f"{_keep_all_words(h)} the dense head's.",
    ]
    if res["models"]["msdnet"]["weights"] == "random":
        out.append(
            "Random weights: a voxel's own occupancy says nothing of its children's, so the points "
            "lost here measure nothing; the shipped models' calibrated gates keep 99 % of the points."
        )
    return out


def old_section(res: dict[str, Any]) -> list[str]:
    """``--against-old``: this run's model against the same weights in the unoptimised graphs."""
    old = res.get("against_old", {})
    if "new_over_old" not in old:
        return []
    out = [
        "",
        "## Against the unoptimised graphs (same weights and input, interleaved in this run)",
        "",
        "| graphs | T_m | head | provider | " + " | ".join(STAGE_NAMES.values()) + " | total ms | points |",
        "|---|---:|---|---|" + "---:|" * (len(STAGE_NAMES) + 2),
    ]
    for key, label in (("old", f"old ({old['old']['up_sampling']} up-sampling)"), ("new", "this run's")):
        r = old[key]
        cells = " | ".join(_fmt(r["stages_ms"].get(s)) for s in STAGE_NAMES)
        out.append(
            f"| {label} | {r['steps']} | {r['head']} | {r['provider']} | {cells} | "
            f"{_fmt(r['total_ms'], 1)} | {r['decoded']} |"
        )
    pairs = old["new_over_old_per_pair"]
    out += [
        "",
        f"New / old total **{_fmt(old['new_over_old'], 3)}** (medians of {old['repeats']} calls each; "
        f"per interleaved pair {min(pairs):.3f}–{max(pairs):.3f}).",
    ]
    return out


def auto_section(res: dict[str, Any]) -> list[str]:
    """``--provider auto``: each model's engine per graph, both engines' times and why (empty otherwise)."""
    auto = res.get("provider_auto") or {}
    if not auto:
        return []
    out = [
        "",
        "## --provider auto: engine per graph (measured at load on the model's own inputs, interleaved)",
        "",
        "| model | graph | engine | onnxruntime ms | OpenVINO ms (f32 or bf16) | why | source |",
        "|---|---|---|---:|---:|---|---|",
    ]
    for kind, rep in auto.items():
        for graph, p in rep["picks"].items():
            ms = p["ms"]
            ov = ms.get("openvino", ms.get("openvino-bf16"))
            out.append(
                f"| {kind} | {graph} | **{p['engine']}** | {_fmt(ms.get('onnxruntime'), 3)} | "
                f"{_fmt(ov, 3)} | {p['reason']} | {'cache' if p['cached'] else 'measured'} |"
            )
    notes = sorted({f"{r['cache']} ({r['cache_note']})" for r in auto.values()})
    return [*out, "", "Cache: " + "; ".join(notes) + "."]


def peers_section(res: dict[str, Any]) -> list[str]:
    """Per stage and engine medians, ours / best peer, and what each engine could not run."""
    p = res.get("peers", {})
    if "stages" not in p:
        return ["", "## Peer engines", "", p.get("note", "not measured")]
    engines = [e for e in ENGINE_LABELS if e in p["totals"]]
    labels = {**ENGINE_LABELS, "onnxruntime": f"ours (--provider {res['provider']})"}
    out = [
        "",
        f"## Peer engines per stage, ms (same graphs, inputs and {p['threads']} threads; "
        f"{p['repeats']} interleaved repeats, medians)",
        "",
        f"Input: {p.get('input', 'one frame, repeated')}.",
        "",
        "| stage | " + " | ".join(labels[e] for e in engines) + " | ours / best peer |",
        "|---|" + "---:|" * (len(engines) + 1),
    ]
    names = {**STAGE_NAMES, OTHER_HEAD: "head ours does not run"}
    for stage, row in p["stages"].items():
        cells = [_fmt(row[e]["median"]) if e in row else "–" for e in engines]
        if row.get("ours_is") and cells:
            cells[0] += "†"
        ratio = row.get("engine_over_best_peer")
        best = ENGINE_LABELS.get(row.get("best_peer", ""), "")
        last = f"{_fmt(ratio, 3)} ({best})" if stage != OTHER_HEAD else "–"
        out.append(f"| {names.get(stage, stage)} ({row['graph']}) | " + " | ".join(cells) + f" | {last} |")
    cells = [
        _fmt(p["totals"][e]["median_ms"]) + ("*" if p["totals"][e]["substituted"] else "") for e in engines
    ]
    best = ENGINE_LABELS.get(p.get("best_peer") or "", "")
    out.append(
        "| **total** | " + " | ".join(cells) + f" | **{_fmt(p['engine_over_best_peer'], 3)}** ({best}) |"
    )
    if p.get("best_f32_peer") and p["best_f32_peer"] != p.get("best_peer"):
        out += [
            "",
            f"Against the full-precision peers only: ours / "
            f"{ENGINE_LABELS.get(p['best_f32_peer'], p['best_f32_peer'])} "
            f"**{_fmt(p['engine_over_best_f32_peer'], 3)}**.",
        ]
    if OTHER_HEAD in p["stages"]:
        out += [
            "",
            "A peer's total and head ratio count the faster of its two head graphs (a user of that "
            "engine would run that one); ours counts the head it runs.",
        ]
    shared = sorted({ENGINE_LABELS[r["ours_is"]] for r in p["stages"].values() if r.get("ours_is")})
    if shared:
        out += [
            "",
            f"† ours runs {' / '.join(shared)} on the stages marked (the graph, precision and settings "
            "of that peer): its calls there are that peer's, timed once.",
        ]
    out += ["", "\\* onnxruntime's time stands in for the stages that engine could not run:"]
    for stage, row in p["stages"].items():
        for engine, why in row["failed"].items():
            out.append(f"- {ENGINE_LABELS[engine]}, {names.get(stage, stage)}: {why}")
    return out


def _keep_all_words(h: dict[str, Any]) -> str:
    """How the keep-every-point gate's points compare with the dense head's."""
    if h["keep_all_equal"]:
        return "equal"
    if h.get("keep_all_close"):
        return "equal within 0.1 mm (the same sums in another order) to"
    if h.get("keep_all_apart_at_threshold") is not None:
        return (
            f"equal within 0.1 mm, but for {h['keep_all_apart_at_threshold']} points one head decodes "
            "alone, each within 1e-5 of the threshold (rounding puts it on either side), to"
        )
    return "DIFFER FROM"
