"""Outputs of ``msdnet-bench latency``: results.json, results.md and three PNG plots.

Everything is written atomically (a temporary file in the same folder, then ``os.replace``);
non-finite numbers become JSON ``null`` so results.json stays strict JSON.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from msdnet.benchmarks.latency.before import before_goal_rows, before_section  # noqa: E402
from msdnet.benchmarks.latency.models import publish_temp, write_json_atomic, write_text_atomic  # noqa: E402
from msdnet.benchmarks.latency.peer_report import (  # noqa: E402
    auto_section,
    goal_rows,
    head_section,
    old_section,
    peers_section,
)

# MSDNet Table IV (VoD, one RTX 4090): runtime s, parameters M
PAPER_TABLE4 = {"r2dm": (0.76, 31.1), "r2ldm": (0.96, 40.3), "msdnet": (0.10, 20.5)}
# MSDNet Table III: T_m -> (CD, MHD x1e-2, JSD, MMD x1e-4, runtime s), as printed
PAPER_TABLE3 = {
    3: (6.02, 73.26, 0.22, 6.48, 0.08),
    10: (5.34, 65.94, 0.21, 5.63, 0.09),
    50: (5.16, 58.98, 0.21, 5.51, 0.10),
    100: (5.16, 64.07, 0.20, 5.40, 0.13),
}
STAGE_LABELS = {
    "voxelize_rulebooks": "voxelize + rulebooks",
    "encoder": "encoder",
    "rgfd_adapter": "RGFD + adapter (R2LDM: draw x_T)",
    "ddim_loop": "DDIM loop",
    "recon_head": "reconstruction head",
    "decode": "decode",
    "total": "total",
}
PAPER_FRAME_GOAL_S = 0.25  # paper preset on this 2-core CPU
LITE_STREAM_MS = 25.0  # goal: a trained lite model, ms per frame at 2 threads


def goals(res: dict[str, Any]) -> list[dict[str, Any]]:
    """The latency goals as rows {goal, measured, target, met} (met is None when unmeasured)."""
    r = res["ratios"]
    rows = [
        ("MSDNet / R2LDM latency", r["msdnet_over_r2ldm"], "<=", 0.10),
        ("onnxruntime / torch eager, same threads", r["onnx_over_torch"], "<=", 0.5),
        ("onnxruntime / torch eager, torch's best threads", r["onnx_over_best_torch"], "<=", 0.5),
        ("DDIM loop share outside the step graph", r["loop_overhead_share"], "<=", 0.03),
        ("voxelize a radar frame: numba / numpy speedup", r["voxelize_numba_speedup"], ">=", 20.0),
        ("voxelize 100k LiDAR-like points: speedup", r["voxelize_numba_speedup_100k"], ">=", 20.0),
        ("voxelize + rulebooks of a radar frame: speedup", r["voxelize_rulebooks_numba_speedup"], ">=", 20.0),
        ("voxelize a radar frame, ms", res["voxelize"]["numba_ms"], "<", 1.0),
        ("voxelize + rulebooks of a radar frame, ms", res["voxelize"]["numba_with_rulebooks_ms"], "<", 1.0),
        ("step graph FLOP rate / sgemm (best of each)", r["step_flops_over_peak"], ">=", 0.5),
    ]
    if res["preset"] == "paper":
        rows.append(("paper preset, s per frame", res["stages_ms"]["total"]["median"] / 1e3, "<=", 0.25))
    stream = (res.get("stream") or {}).get("stages_ms")
    if res["preset"] == "lite" and res["models"]["msdnet"]["weights"] != "random" and stream:
        rows.append(("lite model, ms per frame on a stream", stream["total"]["median"], "<=", LITE_STREAM_MS))
    rows += goal_rows(res) + before_goal_rows(res)
    ops: dict[str, Callable[[float, float], bool]] = {
        "<=": lambda a, b: a <= b,
        ">=": lambda a, b: a >= b,
        "<": lambda a, b: a < b,
    }
    out = []
    for name, value, op, target in rows:
        ok = None if value is None or not math.isfinite(value) else bool(ops[op](value, target))
        out.append({"goal": name, "measured": value, "target": f"{op} {target:g}", "met": ok})
    return out


def _clean(obj: Any) -> Any:
    """A JSON-safe copy: non-finite floats -> None, tuples -> lists, numpy scalars -> Python."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if hasattr(obj, "item") and not isinstance(obj, str | bytes):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _fmt(v: Any, nd: int = 2, kind: str = "f") -> str:
    """A table cell: floats with ``nd`` digits (``kind`` f or g), n/a for None / non-finite."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{nd}{kind}}" if isinstance(v, float) else str(v)


def _table(head: list[str], rows: list[list[Any]]) -> list[str]:
    """A markdown table; numbers through :func:`_fmt`."""
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append("| " + " | ".join(c if isinstance(c, str) else _fmt(c) for c in r) + " |")
    return lines


def _header(res: dict[str, Any]) -> list[str]:
    m, rep, mods = res["machine"], res["repeats"], res["models"]

    def la(key: str) -> str:
        return " / ".join(f"{x:.2f}" for x in m[key])

    inp = res["input"]
    out = [
        f"# msdnet-bench latency: preset `{res['preset']}`, provider {res['provider']}, "
        f"{res['threads']} threads",
        "",
        f"Machine: {m['cpu']}, {m['logical_cores']} logical cores, {m['system']}; numpy sgemm "
        f"{m['sgemm_gflops']:.1f} GFLOP/s; onnxruntime {m['onnxruntime']}, numpy {m['numpy']}, "
        f"Python {m['python']}. Load average (1/5/15 min) {la('loadavg_start')} at the start, "
        f"{la('loadavg_end')} at the end: the machine is shared, so absolute times are upper "
        "bounds; the ratios are measured in the same run.",
        "",
        f"Input: {inp['source']} ({inp.get('points_in', '?')} points, {inp.get('points_in_grid', '?')} "
        f"in the grid, {inp.get('voxels', '?')} voxels). Medians over {rep['msdnet']} MSDNet and "
        f"{rep['r2ldm']} R2LDM frames after warm-up; sweeps {rep['sweeps']} frames per point.",
        "",
    ]
    for k, name in (("msdnet", "MSDNet"), ("r2ldm", "R2LDM")):
        d = mods[k]
        out.append(
            f"- {name}: {d['weights']} weights, T = {d['steps']} steps, BEV {d['bev_shape']}, "
            f"threshold {d['threshold']:.4g} ({d['threshold_note']}), "
            f"{res['decoded_points'][k]} decoded points."
        )
    if any(d["weights"] == "random" for d in mods.values()):
        out.append(
            "- Random weights: latency depends on them only through the decoded point count, "
            "which the threshold above fixes."
        )
    if res.get("up_sampling"):
        form = {"conv_transpose": "one ConvTranspose"}.get(
            res["up_sampling"], "1x1x1 conv + 8-D Transpose (the older export form)"
        )
        out.append(f"- Head up-sampling exported as {form}.")
    return out


def _tables(res: dict[str, Any]) -> list[str]:
    st, r2, p = res["stages_ms"], res["r2ldm_stages_ms"], res["params"]
    out = ["", "## Per stage, ms", ""]
    out += _table(
        ["stage", "MSDNet median", "p90", "min", "R2LDM median", "p90", "min"],
        [[STAGE_LABELS[k], *[d[k][q] for d in (st, r2) for q in ("median", "p90", "min")]] for k in st],
    )
    out += _stream_section(res)
    out += useful_section(res)
    out += ["", "## Goals (measured in this run)", ""]
    met = {True: "yes", False: "NO", None: "n/a"}
    out += _table(
        ["goal", "measured", "target", "met"],
        [[g["goal"], _fmt(g["measured"], 3, "g"), g["target"], met[g["met"]]] for g in res["goals"]],
    )
    out += ["", "## Time and parameters per model (paper's Table IV: VoD, RTX 4090; here: this CPU)", ""]
    names = ("r2dm", "r2ldm", "msdnet")
    out += _table(
        ["", "R2DM", "R2LDM", "MSDNet"],
        [
            ["paper runtime, s", *[PAPER_TABLE4[k][0] for k in names]],
            ["measured runtime, s", "-", r2["total"]["median"] / 1e3, st["total"]["median"] / 1e3],
            ["paper parameters, M", *[PAPER_TABLE4[k][1] for k in names]],
            ["measured parameters, M", "-", p["r2ldm"] / 1e6, p["msdnet"] / 1e6],
        ],
    )
    out += ["", "## Quality and time against T_m (paper's Table III: CD and runtime on an RTX 4090)", ""]
    sweep = {row["steps"]: row for row in res["steps_sweep"]}
    qual = {row["steps"]: row for row in res["table3"]["quality"]}
    head = ["T_m", "paper s", "paper CD", "measured total ms", "DDIM loop ms"]
    keys = ["cd", "mhd", "jsd", "mmd", "fscore_0.2", "points"]
    if qual:
        head += ["CD m", "MHD m", "JSD", "MMD", "F@0.2 m", "points"]
    rows = []
    for s in res["table3"]["steps"]:
        row = [s, PAPER_TABLE3[s][4], PAPER_TABLE3[s][0], sweep[s]["ms"], sweep[s]["loop_ms"]]
        rows.append(row + ([_fmt(qual[s][k], 3, "g") for k in keys] if qual else []))
    out += _table(head, rows)
    if not qual:
        out += ["", "Quality columns need a trained --model and --data/--dataset."]
    out += ["", "## Latency against T_m (steps.png)", ""]
    out += _table(
        ["T_m", "total ms", "p90", "min", "DDIM loop ms"],
        [[r["steps"], r["ms"], r["p90"], r["min"], r["loop_ms"]] for r in res["steps_sweep"]],
    )
    out += ["", "## Latency against input points (points.png)", ""]
    out += _table(
        ["points", "voxels", "total ms", "p90", "min", "voxelize + rulebooks ms"],
        [
            [r[k] for k in ("points", "voxels", "ms", "p90", "min", "voxelize_ms")]
            for r in res["points_scaling"]
        ],
    )
    return out


def useful_section(res: dict[str, Any]) -> list[str]:
    """Per graph stage: the FLOPs on occupied voxels only against the machine's sgemm rate
    (``latency/useful``)."""
    rows = res.get("useful_flops") or {}
    if not rows:
        return []
    peak = res["step_graph"]["sgemm_gflops_peak"]
    out = ["", "## Useful-FLOP efficiency per stage", ""]
    out.append(
        "Useful FLOPs: the FLOPs a stage needs on occupied voxels only (the encoder's real neighbour "
        "pairs; the other stages' convolutions at the positions under an input or decoded voxel; the "
        "head counted on the dense reference graph). Efficiency = useful FLOPs / (median time x "
        f"sgemm {peak:.1f} GFLOP/s, the best in this run): how far a stage is from the machine's limit."
    )
    out.append("")
    labels = {**STAGE_LABELS, "graphs": "the four graph stages"}
    out += _table(
        ["stage", "median ms", "graph GFLOP", "useful GFLOP", "useful share", "useful GFLOP/s", "efficiency"],
        [
            [
                labels[k],
                r["ms"],
                _fmt(r["gflop"], 4),
                _fmt(r["gflop_useful"], 4),
                _fmt(r["useful_share"], 3),
                r["useful_gflops_rate"],
                _fmt(r["efficiency"], 4),
            ]
            for k, r in rows.items()
        ],
    )
    return out


def _stream_section(res: dict[str, Any]) -> list[str]:
    """Whole frames on a stream beside the repeated timing input, per stage."""
    s = res.get("stream") or {}
    out = ["", "## Whole frames on a stream, ms", ""]
    if "stages_ms" not in s:
        return out + [f"{s.get('source', 'not run')}."]
    st, sm = res["stages_ms"], s["stages_ms"]
    out.append(
        f"{s['source']} (medians: {s['voxels_median']:.0f} radar voxels, {s['head_voxels_median']:.0f} "
        f"head voxels, {s['decoded_median']:.0f} decoded points), each once after the runs above, as a "
        "sensor feeds them: every input is new to every session. OpenVINO prepares kernels per input "
        "shape, so it is slower here than on the timing input repeated; onnxruntime hardly differs."
    )
    out.append("")
    out += _table(
        ["stage", "timing input repeated, median", "stream median", "p90", "min"],
        [[STAGE_LABELS[k], st[k]["median"], *[sm[k][q] for q in ("median", "p90", "min")]] for k in sm],
    )
    out += ["", f"Stream / repeated input, total: {_fmt(res['ratios'].get('stream_over_repeated'), 3)}."]
    if "heads_ms" in s:
        c, d = s["heads_ms"]["coarse-to-fine"], s["heads_ms"]["dense"]
        out[-1] += (
            f" Both heads on the same frames (each frame run again with the head the pipeline does not "
            f"run): coarse-to-fine median {c['median']:.2f} ms (p90 {c['p90']:.2f}), dense "
            f"{d['median']:.2f} ms (p90 {d['p90']:.2f}); coarse-to-fine / dense head "
            f"{_fmt(s['head_over_dense_head'], 3)}."
        )
    return out


def _details(res: dict[str, Any]) -> list[str]:
    sg, r, t, v = res["step_graph"], res["ratios"], res["torch_eager"], res["voxelize"]
    out = ["", "## Step graph, loop, torch, voxelizer, memory", ""]
    out.append(
        f"- Step graph alone: {sg['ms']:.3f} ms median (p90 {sg['ms_p90']:.3f}), "
        f"{sg['gflop'] * 1e3:.2f} MFLOP: {sg['gflops_rate']:.1f} GFLOP/s at the median, "
        f"{sg['gflops_rate_best']:.1f} at the best block; numpy sgemm best of 20 right after "
        f"{sg['sgemm_gflops_adjacent']:.1f} GFLOP/s, best in this run {sg['sgemm_gflops_peak']:.1f}: "
        f"{r['step_flops_over_peak']:.0%}. "
        f"R2LDM step {sg['r2ldm_step_ms']:.2f} ms."
    )
    out.append(
        f"- DDIM loop against {sg['steps_per_frame']} bare step-graph calls, each pipeline call followed "
        f"by one block: median over the pairs {r['loop_overhead_share']:.2%} outside the graph (the "
        f"ratio); medians {sg['loop_ms']:.2f} vs {sg['bare_loop_ms']:.2f} ms "
        f"({sg['loop_overhead_share_medians']:.2%}); best {sg['loop_best_ms']:.2f} vs "
        f"{sg['bare_loop_best_ms']:.2f} ms ({sg['loop_overhead_share_best']:.2%})."
    )
    if "torch" in t:
        one = t.get("torch_1_thread", {}).get("median")
        out.append(
            f"- torch eager (same weights and inputs, inference_mode): {t['torch']['median']:.2f} ms "
            f"at {t['threads']} threads, {_fmt(one)} ms at 1 thread; onnxruntime graphs (encoder + "
            f"adapter + loop + head) {t['onnxruntime_graphs']['median']:.2f} ms: ratio "
            f"{_fmt(r['onnx_over_torch'], 3)} (same threads), {_fmt(r['onnx_over_best_torch'], 3)} "
            f"(torch's best); max |occupancy difference| {t['max_abs_occupancy_diff']:.2e}."
        )
    else:
        out.append(f"- torch eager: not measured ({t.get('note', '')}).")
    out.append(
        f"- {v['points']} radar points: voxelize numba {v['numba_ms']:.3f} ms, numpy "
        f"{v['numpy_ms']:.3f} ms ({v['speedup']:.1f}x); voxelize + every rulebook numba "
        f"{v['numba_with_rulebooks_ms']:.3f} ms, numpy {v['numpy_with_rulebooks_ms']:.3f} ms "
        f"({v['speedup_with_rulebooks']:.1f}x). 100k LiDAR-like points: voxelize numba "
        f"{v['numba_100k_ms']:.2f} ms, numpy {v['numpy_100k_ms']:.2f} ms ({v['speedup_100k']:.1f}x)."
    )
    out.append(f"- Peak RSS of one msdnet-infer process: {res['peak_memory_mb']['msdnet_infer']:.0f} MiB.")
    i8 = res.get("int8") or {}
    if i8:
        out += ["", "## INT8 step graph (measured, not the default)", ""]
        out.append(
            f"{i8['method']}: step {i8['step_ms_fp32']:.3f} -> {i8['step_ms_int8']:.3f} ms "
            f"({i8['step_speedup']:.2f}x), frame total {i8['total_ms_int8']:.1f} ms; one-step "
            f"relative error {i8['step_rel_error']:.2%}; decoded points {i8['decoded_fp32']} -> "
            f"{i8['decoded_int8']}; Chamfer INT8 vs FP32 {_fmt(i8['chamfer_int8_vs_fp32_m'], 4)} m."
        )
    return out


def markdown(res: dict[str, Any]) -> str:
    """results.md: machine, input, stages, goals, Tables III and IV, sweeps, details, INT8, notes."""
    out = _header(res) + _tables(res) + before_section(res) + head_section(res) + old_section(res)
    out += auto_section(res)
    out += peers_section(res)
    out += _details(res)
    out += ["", "![stages](stages.png) ![steps](steps.png) ![points](points.png)", ""]
    out += [f"- {n}" for n in res.get("notes", [])]
    return "\n".join(out) + "\n"


def _save_figure(fig: Any, path: Path) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110, format="png")
        publish_temp(tmp, path)
    finally:
        plt.close(fig)
        Path(tmp).unlink(missing_ok=True)


def plots(res: dict[str, Any], out: Path) -> list[Path]:
    """stages.png (bar per stage, log scale), steps.png, points.png; -> the paths."""
    keys = [k for k in res["stages_ms"] if k != "total"]
    fig, ax = plt.subplots(figsize=(8, 4))
    x = range(len(keys))
    for off, k, name in ((-0.2, "stages_ms", "MSDNet"), (0.2, "r2ldm_stages_ms", "R2LDM")):
        ax.bar([i + off for i in x], [max(res[k][s]["median"], 1e-3) for s in keys], 0.4, label=name)
    ax.set_xticks(list(x), [STAGE_LABELS[k].split(" (")[0] for k in keys], rotation=20, fontsize=8)
    ax.set(yscale="log", ylabel="median ms", title=f"Per-stage latency, preset {res['preset']}")
    ax.legend()
    fig.tight_layout()
    _save_figure(fig, out / "stages.png")
    paths = [out / "stages.png"]
    sweeps = (
        ("steps_sweep", "steps", "DDIM steps T_m", "loop_ms"),
        ("points_scaling", "points", "input points", "voxelize_ms"),
    )
    for key, col, xlabel, second in sweeps:
        rows = res[key]
        fig, ax = plt.subplots(figsize=(6, 4))
        xs = [r[col] for r in rows]
        ax.plot(xs, [r["ms"] for r in rows], "o-", label="total")
        ax.plot(xs, [r[second] for r in rows], "s--", label=second.removesuffix("_ms"))
        title = f"MSDNet latency vs {col}, preset {res['preset']}"
        ax.set(xlabel=xlabel, ylabel="median ms", title=title, xscale="log" if col == "points" else "linear")
        ax.legend()
        ax.grid(alpha=0.3)
        fig.tight_layout()
        _save_figure(fig, out / f"{col}.png")
        paths.append(out / f"{col}.png")
    return paths


def write_outputs(out: Path, res: dict[str, Any]) -> None:
    """Add the goals to ``res`` and write results.json, results.md and the plots into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    res["goals"] = goals(res)
    plots(res, out)
    write_json_atomic(out / "results.json", _clean(res))
    write_text_atomic(out / "results.md", markdown(res))
