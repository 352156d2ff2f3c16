"""Does a trained R2LDM follow its radar condition? ``msdnet-bench conditioning CKPT``.

On frames of a split (validation by default; never used for training or selection), in torch:

- **eps-MSE per t bucket** (buckets of 100 steps, t drawn uniformly inside each) of the U-Net on the
  frame's normalised teacher latent noised at t, with the frame's **own** condition c = F_r^S, with
  a **shuffled** one (the condition of the frame half the split away, same x_t, t and eps), with a
  **zero** condition, and the linear guess ``sqrt(1 - abar_t) x_t`` (MSE ~abar_t, where the U-Net
  starts). A model that follows its input has own well below shuffled (goal: own <= 0.9 x
  shuffled, mean over t).
- **Samples** from the same x_T with the own and the shuffled condition (``cfg.r2ldm_sample_steps``
  DDIM steps, the step graph's x0 clip): their latent std against the teacher latent's, their
  distance to the teacher latent, and how far the two samples lie apart relative to their size.

Randomness (t, eps, x_T) comes from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
import numpy as np

from msdnet.benchmarks.stages import T_BUCKETS, frame_batches, split_frames, write_markdown_and_json
from msdnet.runtime.errors import one_line_errors
from msdnet.runtime.io.atomic import checks_outputs

EPS_NAMES = ("own", "shuffled", "zero", "linear")  # eps-MSE columns (module docstring)


def conditioning_report(
    checkpoint: Path,
    dataset: str,
    data: Path,
    split: str = "val",
    max_frames: int | None = None,
    sample_frames: int = 8,
    seed: int = 0,
    threads: int | None = None,
    guidance: float | None = None,
) -> dict[str, Any]:
    """The figures above for an R2LDM checkpoint, as a JSON-ready dict; samples use the
    classifier-free guidance ``guidance`` (default: the checkpoint's config, 1 = off)."""
    import torch

    from msdnet.runtime.errors import MsdnetError
    from msdnet.runtime.spec.ddim import alphas_cumprod, step_coefficients
    from msdnet.training.nn.denoiser import ddim_loop
    from msdnet.training.recipe.checkpoint import load_checkpoint

    if threads is not None:
        torch.set_num_threads(threads)
    model, cfg, state = load_checkpoint(checkpoint)
    if state.kind != "r2ldm":
        raise MsdnetError(checkpoint, f"is a {state.kind} checkpoint; conditioning reports on an R2LDM")
    ds, frame_ids = split_frames(state.dataset, dataset, data, split, max_frames)
    if guidance is not None:
        model.step.guidance = float(guidance)
    model.eval()
    latents, conds = [], []  # per usable frame: (1, C, H8, W8) normalised teacher latent, F_r^S
    with torch.no_grad():
        for _, _, batch in frame_batches(ds, frame_ids, cfg):
            latents.append(model._teacher_latent(batch)[0])
            conds.append(model.encoder.encode(batch.radar))
    n = len(latents)
    if n < 2:
        raise MsdnetError(data, f"{n} frame(s) with radar and LiDAR points in the grid; need 2 or more")
    rng = np.random.default_rng(seed)
    abar = alphas_cumprod(cfg.diffusion)
    edges = np.linspace(0, cfg.diffusion.num_train_steps, T_BUCKETS + 1).astype(int)
    mse = {name: [[] for _ in range(T_BUCKETS)] for name in EPS_NAMES}
    with torch.no_grad():
        for i, z in enumerate(latents):
            other = conds[(i + n // 2) % n]  # a frame half the split away
            for k in range(T_BUCKETS):
                t = int(rng.integers(edges[k] + 1, edges[k + 1] + 1))
                eps = torch.from_numpy(rng.standard_normal(tuple(z.shape), dtype=np.float32))
                a = float(abar[t])
                x_t = a**0.5 * z + (1.0 - a) ** 0.5 * eps
                tt = torch.tensor([float(t)])
                for name, cond in (("own", conds[i]), ("shuffled", other), ("zero", torch.zeros_like(other))):
                    mse[name][k].append(float(((model.unet(x_t, tt, cond) - eps) ** 2).mean()))
                mse["linear"][k].append(float(((x_t * (1.0 - a) ** 0.5 - eps) ** 2).mean()))
        coeffs = step_coefficients(
            cfg.diffusion, sample_steps=cfg.r2ldm_sample_steps, start=cfg.diffusion.num_train_steps
        )
        samples = []
        for i in np.linspace(0, n - 1, min(sample_frames, n)).astype(int):
            z = latents[i]
            x_big_t = torch.from_numpy(rng.standard_normal(tuple(z.shape), dtype=np.float32))
            own = ddim_loop(model.step, x_big_t, coeffs, cond=conds[i])
            shuffled = ddim_loop(model.step, x_big_t, coeffs, cond=conds[(i + n // 2) % n])
            samples.append(
                (
                    float(own.std()),
                    float(z.std()),
                    float((own - z).pow(2).mean().sqrt()),
                    float((shuffled - z).pow(2).mean().sqrt()),
                    float((own - shuffled).norm() / own.norm().clamp_min(1e-12)),
                )
            )
    buckets = [
        {"t": [int(edges[k] + 1), int(edges[k + 1])], **{m: float(np.mean(v[k])) for m, v in mse.items()}}
        for k in range(T_BUCKETS)
    ]
    mean = {m: float(np.mean([b[m] for b in buckets])) for m in EPS_NAMES}
    s = np.array(samples, dtype=np.float64)
    return {
        "checkpoint": str(checkpoint),
        "dataset": dataset,
        "split": split,
        "frames": n,
        "seed": seed,
        "eps_mse": {
            "buckets": buckets,
            "mean_over_t": mean,
            "own_over_shuffled": mean["own"] / mean["shuffled"],
        },
        "samples": {
            "frames": len(samples),
            "steps": cfg.r2ldm_sample_steps,
            "x0_clip": cfg.r2ldm_x0_clip,
            "guidance": model.step.guidance,
            "sample_std": float(s[:, 0].mean()),
            "teacher_latent_std": float(s[:, 1].mean()),
            "rms_to_teacher_own": float(s[:, 2].mean()),
            "rms_to_teacher_shuffled": float(s[:, 3].mean()),
            "own_vs_shuffled_relative_difference": float(s[:, 4].mean()),
        },
    }


def conditioning_markdown(doc: dict[str, Any]) -> str:
    """The report as a short Markdown page."""
    e, s = doc["eps_mse"], doc["samples"]
    lines = [
        f"# Conditioning of {doc['checkpoint']}",
        "",
        f"{doc['dataset']} split `{doc['split']}`, {doc['frames']} frames, seed {doc['seed']}.",
        "",
        "## U-Net eps-MSE per t bucket (normalised teacher latents)",
        "",
        "| t | own condition | shuffled condition | zero condition | linear guess sqrt(1 - abar_t) x_t |",
        "|---|---:|---:|---:|---:|",
    ]
    for b in e["buckets"]:
        lines.append(f"| {b['t'][0]}-{b['t'][1]} | " + " | ".join(f"{b[m]:.3f}" for m in EPS_NAMES) + " |")
    m = e["mean_over_t"]
    lines.append("| **mean over t** | " + " | ".join(f"**{m[k]:.3f}**" for k in EPS_NAMES) + " |")
    lines += [
        "",
        f"Own / shuffled: **{e['own_over_shuffled']:.3f}** (goal <= 0.9).",
        "",
        f"## Samples ({s['frames']} frames, {s['steps']} DDIM steps from T, x0 clip {s['x0_clip']:g}, "
        f"guidance {s.get('guidance', 1.0):g})",
        "",
        "| sample std | teacher latent std | RMS to teacher, own | RMS to teacher, shuffled "
        "| own vs shuffled sample, relative |",
        "|---:|---:|---:|---:|---:|",
        f"| {s['sample_std']:.3f} | {s['teacher_latent_std']:.3f} | {s['rms_to_teacher_own']:.3f} | "
        f"{s['rms_to_teacher_shuffled']:.3f} | {100 * s['own_vs_shuffled_relative_difference']:.1f} % |",
    ]
    return "\n".join(lines) + "\n"


def write_report(doc: dict[str, Any], out: Path) -> None:
    """``out/conditioning.json`` and ``out/conditioning.md``, each written atomically."""
    write_markdown_and_json(doc, conditioning_markdown(doc), out, "conditioning")


@click.command("conditioning", context_settings={"help_option_names": ["-h", "--help"]})
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
@click.option("--max-frames", type=click.IntRange(min=2), help="This many frames, spread evenly.")
@click.option("--sample-frames", type=click.IntRange(min=0), default=8, show_default=True,
              help="Frames sampled from x_T with own and shuffled condition.")  # fmt: skip
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of t, eps and x_T.")
@click.option("--guidance", type=click.FloatRange(min=0.0), help="Samples' guidance w [the checkpoint's].")
@click.option("--threads", type=click.IntRange(min=1), help="torch threads.")
@click.option(
    "--out", required=True, type=click.Path(path_type=Path), help="Folder for conditioning.json/.md."
)
@one_line_errors
@checks_outputs(out="into")  # before any work
def conditioning_command(checkpoint: Path, out: Path, **opts: Any) -> None:
    """Does an R2LDM checkpoint follow its radar condition (eps-MSE with own vs shuffled condition
    per t, samples from the same noise under both)?"""
    doc = conditioning_report(checkpoint, **opts)
    write_report(doc, out)
    click.echo(conditioning_markdown(doc))
