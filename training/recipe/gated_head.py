"""Turn a student with the dense head into one with the gated head (``head_kind`` "gated",
``training/nn/head_gated.py``), from the student's own outputs on the fitted part of its training
range (the selection slice and the validation split are never read):

1. **Norm.** The GroupNorm after the 1/2 level's 3x3x3 conv gets fixed statistics, pooled per
   group over every 1/2 voxel of every frame (as one GroupNorm over all those frames would take
   them). The norm before the conv keeps per-frame statistics (``head_gated``): fixed too, it
   fails on frames unlike the training range's (docs/training.md).
2. **The 1/4 occupancy branch as the gate.** The coarse-to-fine graph computes the 1/2 level only
   under the 1/4 voxels whose 1/4 occupancy (Eq. 3 at 1/4) passes the gate, so that occupancy has
   to say where the head decodes points. A dense student's 1/4 branch does not (it is nearly
   flat, so keeping most points needs every voxel). Its 1x1x1 conv (a logistic regression on the
   1/4 features x4) is refit by L-BFGS to the
   largest full-scale occupancy the head itself decodes under each 1/4 voxel (soft BCE targets:
   no threshold). Nothing else changes: the full-scale outputs at gate 0 are those of step 1.

Each frame's noise eps comes from its own seeded generator, so the command is reproducible.

    msdnet-train gated-head CKPT --dataset astyx --data ROOT --out NEW_CKPT
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import click
import numpy as np
import torch
from torch import Tensor, nn
from tqdm import tqdm

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.training.config import ModelConfig
from msdnet.training.data.batch import make_encoder_input
from msdnet.training.data.datasets import make_splits
from msdnet.training.models.assembly import StudentModel, bev_shape, build_model
from msdnet.training.nn.head_gated import FixedGroupNorm, GatedReconHead
from msdnet.training.recipe.checkpoint import CheckpointState, load_checkpoint, save_checkpoint


def gated_student(checkpoint: str | Path) -> tuple[StudentModel, ModelConfig, CheckpointState]:
    """(student with the gated head and the checkpoint's weights, its config, CheckpointState);
    the fixed norm holds the GroupNorm's affine, statistics not yet folded in."""
    dense, cfg, state = load_checkpoint(checkpoint)
    if state.kind != "student":
        raise MsdnetError(checkpoint, f"is a {state.kind} checkpoint; the gated head is for students")
    if cfg.head_kind != "dense":
        raise MsdnetError(checkpoint, f"has head_kind {cfg.head_kind!r}; calibrate a dense head")
    cfg = dataclasses.replace(cfg, head_kind="gated")
    model = build_model("student", cfg)
    model.load_state_dict(dense.state_dict())  # the same keys: the norms' affines as they are
    return model.eval(), cfg, state


def loop_features(
    model: StudentModel, radar_clouds: list[np.ndarray], seed: int, steps: int | None = None
) -> list[Tensor]:
    """Normalised F^D (1, C, H8, W8) of each cloud after ``steps`` DDIM steps (default: the
    config's), eps from ``default_rng([seed, i])``."""
    from msdnet.runtime.spec.ddim import step_coefficients

    cfg = model.cfg
    coeffs = step_coefficients(cfg.diffusion, sample_steps=steps or cfg.diffusion.sample_steps)
    out = []
    with torch.no_grad():
        for i, radar in enumerate(tqdm(radar_clouds, desc="loop features", unit="frame")):
            enc = make_encoder_input([radar], cfg.grid, cfg.max_voxels_radar)
            if enc.features.shape[0] == 0:
                continue
            eps = np.random.default_rng([seed, i]).standard_normal((1, *bev_shape(cfg)), dtype=np.float32)
            out.append(model.denoised(model.reconstructed(enc), torch.from_numpy(eps), coeffs))
    return out


def pooled_statistics(norm: FixedGroupNorm, run: Callable[[], object]) -> tuple[Tensor, Tensor]:
    """The per-group mean and var (G,) of ``norm``'s input over everything ``run()`` passes
    through it, pooled as one GroupNorm over all of it would take them."""
    sums = torch.zeros(norm.num_groups, 3, dtype=torch.float64)  # count, sum, sum of squares

    def pre(mod: FixedGroupNorm, inp: tuple[Tensor, ...]) -> None:
        g = inp[0].reshape(inp[0].shape[0], mod.num_groups, -1).double()  # (B, G, rest)
        sums[:, 0] += g.shape[0] * g.shape[2]
        sums[:, 1] += g.sum(dim=(0, 2))
        sums[:, 2] += g.pow(2).sum(dim=(0, 2))

    hook = norm.register_forward_pre_hook(pre)
    try:
        with torch.no_grad():
            run()
    finally:
        hook.remove()
    mean = sums[:, 1] / sums[:, 0]
    var = (sums[:, 2] / sums[:, 0] - mean.pow(2)).clamp_min(0)
    return mean.float(), var.float()


def calibrate(model: StudentModel, features: list[Tensor]) -> dict[str, list[float]]:
    """Fold statistics into the gated head's fixed norm from ``features`` (once: it must still hold
    the GroupNorm's affine); -> its pooled mean and var per group."""
    head = model.teacher.head
    if not isinstance(head, GatedReconHead):
        raise TypeError("calibrate needs a student with the gated head")
    mean, var = pooled_statistics(head.fixed_norm(), lambda: [model.head.packed(z) for z in features])
    head.fixed_norm().fold(mean, var)
    return {"mean": mean.tolist(), "var": var.tolist()}


def quarter_targets(model: StudentModel, features: list[Tensor]) -> tuple[Tensor, Tensor]:
    """(x4 rows (F * V4, c4), target (F * V4,)): per 1/4 voxel of every frame its features and the
    largest full-scale occupancy the head decodes under it (cropped children count as 0)."""
    head = model.teacher.head
    xs, ts = [], []
    with torch.no_grad():
        for z in features:
            x4, x2 = head._trunk(model.head._f(z))  # (1, c4, D4, H4, W4), (1, c2, D2, H2, W2)
            occ, _ = head._packed_children(x2)  # (1, 8, D2, H2, W2)
            d4, h4, w4 = x4.shape[2:]
            top = torch.zeros(2 * d4, 2 * h4, 2 * w4)
            half = occ[0].amax(0)  # (D2, H2, W2) the largest of each 1/2 voxel's children
            top[: half.shape[0], : half.shape[1], : half.shape[2]] = half
            ts.append(top.reshape(d4, 2, h4, 2, w4, 2).amax((1, 3, 5)).reshape(-1))
            xs.append(x4[0].reshape(x4.shape[1], -1).t())
    return torch.cat(xs), torch.cat(ts)


def fit_quarter_gate(
    model: StudentModel, features: list[Tensor], weight_decay: float = 1e-4
) -> dict[str, float]:
    """Refit the 1/4 occupancy branch to :func:`quarter_targets` (module docstring, step 2);
    -> the fit's BCE before and after, and the share of 1/4 voxels it keeps at 0.5."""
    conv = model.teacher.head.occ[0]
    x, t = quarter_targets(model, features)
    w = conv.weight.detach().reshape(-1).clone().requires_grad_(True)  # (c4,)
    b = conv.bias.detach().clone().requires_grad_(True)  # (1,)
    bce = nn.functional.binary_cross_entropy_with_logits
    before = float(bce(x @ w.detach() + b.detach(), t))
    opt = torch.optim.LBFGS([w, b], max_iter=300, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = bce(x @ w + b, t) + weight_decay * w.pow(2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        conv.weight.copy_(w.reshape(conv.weight.shape))
        conv.bias.copy_(b)
        logits = x @ w + b
    kept = float((logits > 0).float().mean())
    return {"bce_before": before, "bce_after": float(bce(logits, t)), "kept_at_half": kept}


@click.command()
@click.argument("checkpoint", type=click.Path(exists=True, file_okay=False))
@click.option("--dataset", required=True, help="Dataset the student was trained on.")
@click.option("--data", "root", required=True, type=click.Path(exists=True), help="Its root folder.")
@click.option("--out", required=True, type=click.Path(), help="New checkpoint folder.")
@click.option("--holdout", type=float, default=0.15, show_default=True, help="As msdnet-train: left out.")
@click.option("--val-fraction", type=float, default=0.2, show_default=True, help="As msdnet-train.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the frames' noise.")
@click.option("--steps", type=int, default=None, help="DDIM steps [the config's]: the shipped T_m.")
@click.option("--threads", type=int, default=None, help="torch threads.")
@one_line_errors
def main(
    checkpoint: str,
    dataset: str,
    root: str,
    out: str,
    holdout: float,
    val_fraction: float,
    seed: int,
    steps: int | None,
    threads: int | None,
) -> None:
    """Give CHECKPOINT's student the gated head, calibrated on its fitted frames; write it to --out."""
    if threads:
        torch.set_num_threads(threads)
    model, cfg, state = gated_student(checkpoint)
    fit, _ = make_splits(dataset, root, cfg, val_fraction, holdout=holdout)
    clouds = [fit[i][0] for i in range(len(fit))]
    features = loop_features(model, clouds, seed, steps)
    report = calibrate(model, features)
    fit = fit_quarter_gate(model, features)
    save_checkpoint(out, model, cfg, dataclasses.replace(state, init=str(checkpoint)))
    click.echo(f"fixed 1/2 norm: mean {np.round(report['mean'], 3)}, var {np.round(report['var'], 3)}")
    click.echo(
        f"1/4 gate: BCE to the decoded occupancy {fit['bce_before']:.4f} -> {fit['bce_after']:.4f}, "
        f"{fit['kept_at_half']:.1%} of the 1/4 voxels above 0.5"
    )
    click.echo(f"{out}: gated head calibrated on {len(features)} frames of {dataset}")
