"""Is each stage of a trained MSDNet doing its job? ``msdnet-bench stages CKPT``.

On frames of a split (validation by default; never used for training or selection), in torch:

- **Denoiser (Eq. 10).** eps-MSE of the light denoiser on the frame's normalised teacher latent
  noised at t (Eq. 9), per bucket of 100 steps (t drawn uniformly inside it), with the trivial
  baselines beside it: predicting 0 scores 1, ``x_t`` itself (right at t -> T) scores about
  ``abar_t + (1 - sqrt(1 - abar_t))^2``, and the best linear guess ``sqrt(1 - abar_t) x_t`` (where
  the denoiser starts, training/nn/denoiser.py) about ``abar_t`` on unit-variance latents; a
  denoiser that learned the latents' structure beats all three.
- **Noise adapter (Eq. 12).** The gate delta per frame and channel: percentiles over all, the spread
  of the per-frame mean across frames (does it follow the input?) and across channels.
- **Loop (Eq. 13-14).** Distance of F_r^R (before the loop) and F_r^D (after it) to the teacher's
  latent, per BEV cell, mean over non-empty and empty cells; and the Chamfer distance / F@0.5 of
  points decoded from each at the model's threshold, so "does the loop help" is a number.

Randomness (t, eps, the adapter's noise) comes from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click
import numpy as np

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import checks_outputs

T_BUCKETS = 10  # buckets of t over 1..T


def _percentiles(values: np.ndarray) -> dict[str, float]:
    q = np.percentile(values, [0, 5, 50, 95, 100])
    return {k: float(v) for k, v in zip(("min", "p5", "median", "p95", "max"), q, strict=True)}


def split_frames(
    run_dataset: dict[str, Any], dataset: str, root: Path, split: str, max_frames: int | None
) -> tuple[Any, list[str]]:
    """(reader, frame ids) of ``split``: train | val | all, or select = the run's held-out slice of
    its training range (``run_dataset`` = the checkpoint's ``state.dataset``); ``max_frames`` of
    them spread evenly."""
    from msdnet.benchmarks.quality.suite import pick_frames
    from msdnet.runtime.io.datasets import open_dataset

    ds = open_dataset(dataset, root, split if split in ("train", "val") else None)
    ids = list(ds.frame_ids)
    if split == "select":  # model selection slice
        first, last, _ = run_dataset["val_frames"]
        if first not in ids or last not in ids:
            raise MsdnetError(root, f"has no frames {first}..{last} (the run's selection slice)")
        ids = ids[ids.index(first) : ids.index(last) + 1]
    return ds, pick_frames(ids, max_frames)


def frame_batches(ds: Any, frame_ids: list[str], cfg: Any) -> Iterator[tuple[np.ndarray, np.ndarray, Any]]:
    """(radar (N, R) float32 in ``cfg.radar_columns``, LiDAR (M, 3) float32 [x, y, z], the
    collated batch of that one frame) for each frame with radar and LiDAR points in the grid."""
    from msdnet.runtime.io.datasets.preprocess import preprocess_frame
    from msdnet.training.data.batch import collate

    for fid in frame_ids:
        frame = preprocess_frame(ds.get(fid), cfg.grid)
        radar = np.ascontiguousarray(frame.radar.select(cfg.radar_columns).points, dtype=np.float32)
        lidar = np.ascontiguousarray(frame.lidar.select(cfg.lidar_columns).points, dtype=np.float32)
        if len(radar) and len(lidar):
            yield radar, lidar, collate([(radar, lidar)], cfg)


def write_markdown_and_json(doc: dict[str, Any], markdown: str, out: Path, stem: str) -> None:
    """``out/<stem>.json`` (the doc) and ``out/<stem>.md`` (the page), each written atomically."""
    from msdnet.runtime.io.atomic import atomic_output

    out.mkdir(parents=True, exist_ok=True)
    with atomic_output(out / f"{stem}.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    with atomic_output(out / f"{stem}.md") as tmp:
        tmp.write_text(markdown, encoding="utf-8")


def stage_report(
    checkpoint: Path,
    dataset: str,
    root: Path,
    split: str = "val",
    max_frames: int | None = None,
    seed: int = 0,
    threshold: float | None = None,
    threads: int | None = None,
) -> dict[str, Any]:
    """The figures above for a student checkpoint, as a JSON-ready dict."""
    import torch

    from msdnet.runtime.engine.decode import decode_occupancy
    from msdnet.runtime.errors import MsdnetError
    from msdnet.runtime.metrics.cloud import score_frame
    from msdnet.runtime.metrics.crop import crop_to_grid, xy_range
    from msdnet.runtime.spec.ddim import alphas_cumprod, step_coefficients
    from msdnet.training.nn.adapter import NoiseAdapter
    from msdnet.training.recipe.checkpoint import load_checkpoint

    if threads is not None:
        torch.set_num_threads(threads)
    model, cfg, state = load_checkpoint(checkpoint)
    if state.kind != "student":
        raise MsdnetError(checkpoint, f"is a {state.kind} checkpoint; stages reports on a student")
    thr = cfg.threshold if threshold is None else threshold
    ds, frame_ids = split_frames(state.dataset, dataset, root, split, max_frames)
    rng = np.random.default_rng(seed)
    abar = alphas_cumprod(cfg.diffusion)
    big_t = cfg.diffusion.num_train_steps
    edges = np.linspace(0, big_t, T_BUCKETS + 1).astype(int)  # bucket k: t in (edges[k], edges[k+1]]
    # eps-MSE per t bucket of the denoiser and of the three baselines (module docstring)
    mse: dict[str, list[list[float]]] = {
        name: [[] for _ in range(T_BUCKETS)] for name in ("denoiser", "zero", "x_t", "linear")
    }
    gates, dist, pts = [], {"before_loop": [], "after_loop": []}, {"before_loop": [], "after_loop": []}
    coeffs = step_coefficients(cfg.diffusion)
    model.eval()
    with torch.no_grad():
        for _, lidar, batch in frame_batches(ds, frame_ids, cfg):
            z, nonempty = model._teacher_latent(batch)  # (1, C, H8, W8) normalised, (1, H8, W8)
            for k in range(T_BUCKETS):
                t = int(rng.integers(edges[k] + 1, edges[k + 1] + 1))
                eps = torch.from_numpy(rng.standard_normal(tuple(z.shape), dtype=np.float32))
                a = float(abar[t])
                x_t = a**0.5 * z + (1.0 - a) ** 0.5 * eps
                pred = model.denoiser(x_t, torch.tensor([float(t)]))
                mse["denoiser"][k].append(float(((pred - eps) ** 2).mean()))
                mse["zero"][k].append(float((eps**2).mean()))
                mse["x_t"][k].append(float(((x_t - eps) ** 2).mean()))
                mse["linear"][k].append(float(((x_t * (1.0 - a) ** 0.5 - eps) ** 2).mean()))
            f_r = model.reconstructed(batch.radar)
            noise = torch.from_numpy(rng.standard_normal(tuple(f_r.shape), dtype=np.float32))
            if isinstance(model.adapter, NoiseAdapter) and cfg.use_dgfd:
                gates.append(model.adapter.gate(f_r)[0, :, 0, 0].numpy())  # (C,)
            f_d = model.denoised(f_r, noise, coeffs)
            ref = crop_to_grid(lidar, cfg.grid)
            ne = nonempty[0]
            for key, feat in (("before_loop", f_r), ("after_loop", f_d)):
                d = torch.linalg.vector_norm(feat - z, dim=1)[0]  # (H8, W8)
                dist[key].append((float(d[ne].mean()) if ne.any() else np.nan, float(d[~ne].mean())))
                occ, off = model.head(feat)
                p, _ = decode_occupancy(occ[0, 0].numpy(), off[0].numpy(), cfg.grid, thr)
                p = crop_to_grid(p, cfg.grid)
                if len(p) and len(ref):
                    s = score_frame(p, ref, xy_range(cfg.grid))
                    pts[key].append((s.cd, s.mhd, s.fscore[0.5], len(p)))
    if not dist["after_loop"]:
        raise MsdnetError(root, "no frame with radar and LiDAR points in the grid")
    buckets = [
        {
            "t": [int(edges[k] + 1), int(edges[k + 1])],
            **{name: float(np.mean(v[k])) for name, v in mse.items()},
        }
        for k in range(T_BUCKETS)
    ]
    out: dict[str, Any] = {
        "checkpoint": str(checkpoint),
        "dataset": dataset,
        "split": split,
        "frames": len(dist["after_loop"]),
        "seed": seed,
        "threshold": thr,
        "config": {
            "use_rgfd": cfg.use_rgfd,
            "use_dgfd": cfg.use_dgfd,
            "use_adapter": cfg.use_adapter,
            "latent_normalised": bool(cfg.latent_norm),
            "train_sample_steps": cfg.train_sample_steps,
            "sample_steps": cfg.diffusion.sample_steps,
        },
        "eps_mse": {
            "buckets": buckets,
            "mean_over_t": {name: float(np.mean([b[name] for b in buckets])) for name in mse},
        },
    }
    if gates:
        g = np.stack(gates)  # (frames, C)
        out["gate"] = {
            "all": _percentiles(g.ravel()),
            "frame_mean": _percentiles(g.mean(axis=1)),
            "std_across_frames_per_channel_mean": float(g.std(axis=0).mean()),
            "std_across_channels_mean": float(g.std(axis=1).mean()),
        }
    out["loop"] = {}
    for key in dist:
        arr = np.array(dist[key], dtype=np.float64)
        sc = np.array(pts[key], dtype=np.float64) if pts[key] else np.full((1, 4), np.nan)
        out["loop"][key] = {
            "latent_distance_nonempty": float(np.nanmean(arr[:, 0])),
            "latent_distance_empty": float(np.nanmean(arr[:, 1])),
            "cd": float(sc[:, 0].mean()),
            "mhd": float(sc[:, 1].mean()),
            "fscore@0.5": float(sc[:, 2].mean()),
            "points": float(sc[:, 3].mean()),
            "decoded_frames": len(pts[key]),
        }
    return out


def stage_markdown(doc: dict[str, Any]) -> str:
    """The report as a short Markdown page."""
    lines = [
        f"# Stages of {doc['checkpoint']}",
        "",
        f"{doc['dataset']} split `{doc['split']}`, {doc['frames']} frames, seed {doc['seed']}, "
        f"threshold {doc['threshold']:g}. Config: {doc['config']}.",
        "",
        "## Denoiser eps-MSE per t bucket (normalised teacher latents; predicting 0 scores ~1)",
        "",
        "| t | denoiser | predict 0 | predict x_t | linear guess sqrt(1 - abar_t) x_t |",
        "|---|---:|---:|---:|---:|",
    ]
    for b in doc["eps_mse"]["buckets"]:
        cells = " | ".join(f"{b[k]:.3f}" for k in ("zero", "x_t", "linear"))
        lines.append(f"| {b['t'][0]}-{b['t'][1]} | {b['denoiser']:.3f} | {cells} |")
    m = doc["eps_mse"]["mean_over_t"]
    cells = " | ".join(f"{m[k]:.3f}" for k in ("zero", "x_t", "linear"))
    lines.append(f"| **mean over t** | **{m['denoiser']:.3f}** | {cells} |")
    if "gate" in doc:
        g = doc["gate"]
        lines += ["", "## Adapter gate delta (Eq. 12: x_m = delta F_r^R + (1 - delta) eps)", "",
                  "| over | min | p5 | median | p95 | max |", "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
        for key, label in (("all", "frames x channels"), ("frame_mean", "per-frame mean")):
            q = g[key]
            cells = " | ".join(f"{q[k]:.4f}" for k in ("min", "p5", "median", "p95", "max"))
            lines.append(f"| {label} | {cells} |")
        lines += [
            "",
            f"Std across frames (mean over channels): {g['std_across_frames_per_channel_mean']:.4f}; "
            f"std across channels (mean over frames): {g['std_across_channels_mean']:.4f}.",
        ]
    lines += ["", "## Before and after the DDIM loop", "",
              "| features | distance to teacher, non-empty cells | empty cells | CD (m) | MHD (m) "
              "| F@0.5 | points |",
              "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for key, label in (("before_loop", "F_r^R (no loop)"), ("after_loop", "F_r^D (loop)")):
        r = doc["loop"][key]
        lines.append(
            f"| {label} | {r['latent_distance_nonempty']:.3f} | {r['latent_distance_empty']:.3f} | "
            f"{r['cd']:.3f} | {r['mhd']:.3f} | {r['fscore@0.5']:.3f} | {r['points']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def write_report(doc: dict[str, Any], out: Path) -> None:
    """``out/stages.json`` and ``out/stages.md``, each written atomically."""
    write_markdown_and_json(doc, stage_markdown(doc), out, "stages")


@click.command("stages", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("checkpoint", type=click.Path(path_type=Path))
@click.option("--dataset", required=True, type=click.Choice(["vod", "astyx", "sim"]), help="Data layout.")
@click.option("--data", required=True, type=click.Path(path_type=Path), help="Dataset root.")
@click.option(
    "--split",
    type=click.Choice(["train", "val", "all", "select"]),
    default="val",
    show_default=True,
    help="Frames: a split, or select = the run's held-out selection slice of its training range.",
)
@click.option("--max-frames", type=click.IntRange(min=1), help="This many frames, spread evenly.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of t, eps and the adapter noise.")
@click.option("--threshold", type=float, help="Decoding threshold [the checkpoint's].")
@click.option("--threads", type=click.IntRange(min=1), help="torch threads.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Folder for stages.json/.md.")
@one_line_errors
@checks_outputs(out="into")  # before any work
def stages_command(checkpoint: Path, out: Path, **opts: Any) -> None:
    """Does each stage of a student checkpoint do its job (denoiser eps-MSE per t, adapter gate,
    features and points before / after the DDIM loop)?"""
    doc = stage_report(checkpoint, opts["dataset"], opts["data"], opts["split"], opts["max_frames"],
                       opts["seed"], opts["threshold"], opts["threads"])  # fmt: skip
    write_report(doc, out)
    click.echo(stage_markdown(doc))
