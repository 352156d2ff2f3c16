"""``msdnet-train``: train the LiDAR teacher, the MSDNet student or the R2LDM baseline.

    msdnet-train teacher --dataset astyx --data ../shared/data/astyx_hires2019 --preset lite --out runs/t
    msdnet-train student --dataset astyx --data ... --preset lite --teacher runs/t/best --out runs/s
    torchrun --nproc_per_node=2 -m msdnet.training.cli teacher ...   # data-parallel (gloo on CPU)

Writes ``OUT/last``, ``OUT/best`` (checkpoints) and ``OUT/log.jsonl``; ``--resume`` continues
``OUT/last`` after a kill. Bad input and a NaN loss end in one line ``error: ...`` and exit 2.
"""

from __future__ import annotations

import copy
import dataclasses
import os
from dataclasses import replace
from functools import partial
from pathlib import Path

import click
import torch

from msdnet.runtime.errors import MsdnetError, one_line_errors
from msdnet.runtime.io.atomic import checks_outputs
from msdnet.training.config import (
    MODEL_PRESETS,
    R2LDM_LR,
    TRAIN_PRESETS,
    AugmentConfig,
    ModelConfig,
    TrainConfig,
)
from msdnet.training.data.batch import collate
from msdnet.training.data.datasets import DATASETS, PairDataset, config_for_dataset, make_splits
from msdnet.training.models.assembly import MODEL_KINDS, build_model
from msdnet.training.nn.heads import HEAD_KINDS
from msdnet.training.recipe.checkpoint import (
    config_diff,
    load_checkpoint,
    publish_checkpoint,
    read_checkpoint,
)
from msdnet.training.recipe.distributed import DistInfo, init_distributed, shutdown_distributed
from msdnet.training.recipe.loop import RunSpec, occupancy_counts, train


def _choice(value: str, choices: tuple[str, ...] | list[str], what: str) -> str:
    if value not in choices:
        raise MsdnetError(None, f"unknown {what} {value!r} (choose from {', '.join(choices)})")
    return value


# config fields the teacher does not use: R2LDM's, the student's, and the latent normalisation
# that is measured on the teacher when a student / R2LDM run starts
R2LDM_ONLY = (
    "r2ldm_channels",
    "r2ldm_cond_channels",
    "r2ldm_x0_clip",
    "r2ldm_cond_dropout",
    "r2ldm_guidance",
    "r2ldm_sample_steps",
)
NOT_TEACHER = (
    *R2LDM_ONLY,
    "train_sample_steps",
    "denoiser_hidden",
    "time_embed_dim",
    "latent_norm",
    "use_rgfd",
    "use_dgfd",
    "use_adapter",
    "diffusion",
)
ABLATIONS = {"rgfd": "use_rgfd", "dgfd": "use_dgfd", "adapter": "use_adapter"}  # --ablate NAME -> field


def _teacher(path: Path, cfg: ModelConfig) -> torch.nn.Module:
    """The trained teacher from its checkpoint, after checking it fits ``cfg``."""
    folder, tcfg, tstate = read_checkpoint(path)
    if tstate.kind != "teacher":
        raise MsdnetError(folder, f"is a {tstate.kind} checkpoint, not a teacher")
    # the student-only loss settings do not concern the teacher either
    student_only = {
        k: getattr(tcfg.losses, k)
        for k in (
            "lambdas",
            "denoiser_distill_grad",
            "denoiser_grad_steps",
            "denoiser_grad_ratio",
            "adapter_align",
            "r2ldm_cond_align",
        )
    }
    differs = config_diff(tcfg, replace(cfg, losses=replace(cfg.losses, **student_only)), ignore=NOT_TEACHER)
    if differs:
        fields = ", ".join(differs)
        raise MsdnetError(folder, f"teacher config differs from this run: {fields}"[:300])
    return load_checkpoint(folder)[0]


def _student_options(
    cfg: ModelConfig, kind: str, grad: str | None, hidden: int | None, embed: int | None
) -> ModelConfig:
    """--denoiser-grad MODE[:K[:R]], --denoiser-hidden, --time-embed into the config."""
    if kind != "student" and (grad, hidden, embed) != (None, None, None):
        raise MsdnetError(None, "--denoiser-grad, --denoiser-hidden and --time-embed are student options")
    if hidden is not None or embed is not None:
        if (hidden is not None and hidden < 1) or (embed is not None and (embed < 2 or embed % 2)):
            raise MsdnetError(None, "--denoiser-hidden must be >= 1 and --time-embed even and >= 2")
        cfg = replace(
            cfg, denoiser_hidden=hidden or cfg.denoiser_hidden, time_embed_dim=embed or cfg.time_embed_dim
        )
    if grad is None:
        return cfg
    mode, *rest = grad.split(":")
    try:
        steps = int(rest[0]) if rest and rest[0] else 0
        ratio = float(rest[1]) if len(rest) > 1 else 0.0
    except ValueError:
        steps, ratio = -1, -1.0
    if (
        mode not in ("detach", "joint")
        or len(rest) > 2
        or steps < 0
        or ratio < 0
        or (mode == "detach" and rest)
    ):
        raise MsdnetError("--denoiser-grad", f"expected detach, joint, joint:K or joint:K:R, got {grad!r}")
    losses = replace(
        cfg.losses,
        denoiser_distill_grad=mode == "joint",
        denoiser_grad_steps=steps,
        denoiser_grad_ratio=ratio,
    )
    return replace(cfg, losses=losses)


def _plan(
    kind: str,
    out: Path,
    resume: bool,
    epochs: int | None,
    tcfg: TrainConfig,
    overrides: dict,
    recipe: str = "improved",
) -> tuple[int, TrainConfig]:
    """(epochs, train config) of the run. Fresh: --epochs or the preset's, the preset's config
    with the options given. Resume: what OUT/last planned, with the options given (checked)."""
    has_last = (out / "last").exists() or (out / "last.old").exists()
    if not resume:
        if has_last:
            raise MsdnetError(out, "already holds a checkpoint: pass --resume, or choose another --out")
        n = epochs or (tcfg.epochs_teacher if kind == "teacher" else tcfg.epochs_student)
        if kind == "r2ldm":
            tcfg = replace(tcfg, lr=R2LDM_LR)
        if recipe == "published":
            from msdnet.training.published_config import published_train_config

            tcfg = published_train_config(tcfg, kind)
        return n, replace(tcfg, **overrides)
    if not has_last:
        raise MsdnetError(out, "has no checkpoint 'last' to resume")
    state = read_checkpoint(out / "last")[2]
    return epochs or state.epochs, replace(state.train, **overrides)


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("kind", metavar="teacher|student|r2ldm")
@click.option("--dataset", required=True, help="vod | astyx | sim (simulator output, VoD layout).")
@click.option("--data", "data", required=True, type=click.Path(path_type=Path), help="Dataset root folder.")
@click.option("--preset", default="lite", show_default=True, help="Model/train preset: tiny | lite | paper.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Run folder.")
@click.option("--epochs", type=int, default=None, help="Epochs (default: the preset's).")
@click.option(
    "--recipe",
    default="improved",
    show_default=True,
    help="R2LDM recipe: improved (ours) | published (the authors' code; its teacher is the LPCR stage 1).",
)
@click.option("--resume", is_flag=True, help="Continue OUT/last (weights, optimizer, schedule, position).")
@click.option("--teacher", type=click.Path(path_type=Path), default=None, help="Teacher checkpoint.")
@click.option("--batch-size", type=int, default=None, help="Frames per step and process.")
@click.option("--lr", type=float, default=None, help="Peak learning rate (OneCycleLR).")
@click.option("--seed", type=int, default=None, help="Seed for weights, order and noise.")
@click.option("--val-fraction", type=float, default=0.2, show_default=True, help="Share of frames for val.")
@click.option("--frames", "max_frames", type=int, default=None, help="Use only the first N frames.")
@click.option("--radar-frames", type=int, default=1, show_default=True, help="VoD radar scans accumulated.")
@click.option("--save-every", type=int, default=0, show_default=True, help="Also save every N steps.")
@click.option("--workers", type=int, default=None, help="DataLoader worker processes.")
@click.option(
    "--metric-frames", type=int, default=64, show_default=True, help="Val frames with occupancy metrics."
)
@click.option("--device", default="cpu", show_default=True, help="torch device (cuda: one GPU per process).")
@click.option(
    "--threads",
    type=int,
    default=None,
    help="torch CPU threads per process (default: cores / processes). Fixed so runs are reproducible.",
)
@click.option(
    "--occ-pos-weight",
    type=float,
    default=None,
    help="Weight of occupied voxels in the occupancy loss (Eq. 5) [1, the paper].",
)
@click.option("--zeta", type=float, default=None, help="Offset weight of Eq. 7 [10, the paper].")
@click.option(
    "--full-scale-rate",
    type=float,
    default=None,
    help="Share of the full scale far from the LiDAR points scored per step, reweighted so the loss "
    "is unbiased; the rest is not computed [1 = every voxel].",
)
@click.option(
    "--holdout",
    type=float,
    default=0.15,
    show_default=True,
    help="Share of the training range (its last frames) held out to pick the best checkpoint; "
    "the validation split is never read (0: select on the validation split).",
)
@click.option(
    "--augment/--no-augment",
    default=True,
    show_default=True,
    help="Seeded mirror / yaw / scale / radar dropout of the training frames.",
)
@click.option(
    "--lambdas",
    default=None,
    help="Eq. 15 weights of recon, Eq. 8, Eq. 14, Eq. 10 as four numbers a,b,c,d [1,0.01,5,10].",
)
@click.option("--start-step", type=int, default=None, help="Student diffusion start step m [preset: 100].")
@click.option(
    "--adapter-align",
    type=float,
    default=None,
    help="Weight of the noise adapter's alignment loss [1; 0 = gate trained end to end].",
)
@click.option(
    "--cond-align",
    type=float,
    default=None,
    help="R2LDM: weight of the condition's auxiliary regression of the teacher latent [0 = as published].",
)
@click.option(
    "--cond-dropout",
    type=float,
    default=None,
    help="R2LDM: share of frames trained without condition, for classifier-free guidance [0].",
)
@click.option(
    "--ablate",
    multiple=True,
    help="Student ablation (repeatable): rgfd (no RGFD), dgfd (no adapter and loop), adapter (Eq. 9 at m).",
)
@click.option(
    "--latent-frames",
    type=int,
    default=64,
    show_default=True,
    help="Training frames on which a student / R2LDM run measures the teacher's latent shift and scale.",
)
@click.option(
    "--ema",
    type=float,
    default=None,
    help="Decay of an EMA of the weights, scored and kept in best/ [0 = off].",
)
@click.option(
    "--denoiser-grad",
    default=None,
    help="Student: how Eq. 14 reaches the denoiser's weights through the loop: detach (Eq. 10 only), "
    "joint (Eq. 15), joint:K (last K loop steps), joint:K:R or joint::R (scaled to R x Eq. 10's norm).",
)
@click.option(
    "--loop-steps",
    type=int,
    default=None,
    help="Student: DDIM steps T_m of the loop, in training and the exported default [preset: 50].",
)
@click.option("--denoiser-hidden", type=int, default=None, help="Student: light denoiser width [32].")
@click.option("--time-embed", type=int, default=None, help="Student: denoiser time-embedding width [64].")
@click.option(
    "--head", "head_kind", default=None, help="Recon head: dense | gated | gated8 | sparse [dense]."
)
@click.option(
    "--head-only",
    is_flag=True,
    help="Train only the head: a teacher's on its --init encoder, a student's on its own F_r^D.",
)
@click.option(
    "--distill",
    "distill_steps",
    type=int,
    default=None,
    help="Student: few-step distillation of the --init loop: its denoiser alone learns to reach in "
    "--loop-steps K steps what the --init loop reaches in N (the model's config is --init's).",
)
@click.option(
    "--distill-head",
    type=float,
    default=None,
    help="With --distill: weight of the full-scale occupancy MSE (frozen head) beside the latent MSE [0].",
)
@click.option(
    "--publish",
    type=click.Path(path_type=Path),
    default=None,
    help="When the run has finished its epochs, copy best/ here as weights and checkpoint.json only "
    "(no optimizer state): small enough to commit, e.g. checkpoints/MODEL/teacher.",
)
@click.option(
    "--init",
    type=click.Path(path_type=Path),
    default=None,
    help="Start from this checkpoint's weights (same kind and config; fresh optimizer and schedule).",
)
@one_line_errors
@checks_outputs(out="into")  # the run folder, before any work
def main(
    kind: str,
    dataset: str,
    data: Path,
    preset: str,
    out: Path,
    epochs: int | None,
    recipe: str,
    resume: bool,
    teacher: Path | None,
    batch_size: int | None,
    lr: float | None,
    seed: int | None,
    val_fraction: float,
    max_frames: int | None,
    radar_frames: int,
    save_every: int,
    workers: int | None,
    metric_frames: int,
    device: str,
    threads: int | None,
    occ_pos_weight: float | None,
    zeta: float | None,
    full_scale_rate: float | None,
    holdout: float,
    augment: bool,
    lambdas: str | None,
    start_step: int | None,
    adapter_align: float | None,
    cond_align: float | None,
    cond_dropout: float | None,
    ablate: tuple[str, ...],
    latent_frames: int,
    ema: float | None,
    loop_steps: int | None,
    denoiser_grad: str | None,
    denoiser_hidden: int | None,
    time_embed: int | None,
    head_kind: str | None,
    head_only: bool,
    distill_steps: int | None,
    distill_head: float | None,
    publish: Path | None,
    init: Path | None,
) -> None:
    """Train KIND (teacher, student or r2ldm) on a dataset; student and r2ldm need --teacher."""
    _choice(kind, MODEL_KINDS, "model kind")
    _choice(dataset, DATASETS, "dataset")
    _choice(preset, sorted(MODEL_PRESETS), "preset")
    if epochs is not None and epochs < 1:
        raise MsdnetError(None, f"--epochs must be >= 1, got {epochs}")
    if ema is not None and not 0 <= ema < 1:
        raise MsdnetError("--ema", f"is a decay in [0, 1), got {ema}")
    options = {"batch_size": batch_size, "lr": lr, "seed": seed, "num_workers": workers, "ema_decay": ema}
    if head_only:
        if kind == "r2ldm" or init is None:
            raise MsdnetError("--head-only", "trains only the head of a teacher or student --init checkpoint")
        options["head_only"] = True
    if distill_steps is not None:
        if kind != "student" or (init is None and not resume) or head_only or loop_steps is None:
            raise MsdnetError("--distill", "distils a student --init checkpoint's loop: give --loop-steps K")
        options["distill_steps"] = distill_steps
        if distill_head is not None and distill_head < 0:
            raise MsdnetError("--distill-head", f"must be >= 0, got {distill_head}")
        options["distill_head"] = distill_head
    elif distill_head is not None:
        raise MsdnetError("--distill-head", "is a --distill weight")
    if not augment:
        options["augment"] = AugmentConfig.off()
    overrides = {k: v for k, v in options.items() if v is not None}
    from msdnet.training.published_config import RECIPES, with_recipe

    _choice(recipe, RECIPES, "recipe")
    if recipe == "published" and kind == "student":
        raise MsdnetError("--recipe", "published is an R2LDM recipe: train teacher (stage 1) or r2ldm")
    n_epochs, tcfg = _plan(kind, out, resume, epochs, TRAIN_PRESETS[preset], overrides, recipe)
    if tcfg.batch_size < 1 or tcfg.lr <= 0 or tcfg.num_workers < 0:
        raise MsdnetError(None, "--batch-size must be >= 1, --lr > 0 and --workers >= 0")
    cfg = config_for_dataset(MODEL_PRESETS[preset], dataset)
    if recipe == "published":
        cfg = with_recipe(cfg, recipe)
    if occ_pos_weight is not None:
        if occ_pos_weight <= 0:
            raise MsdnetError("--occ-pos-weight", f"must be > 0, got {occ_pos_weight}")
        cfg = dataclasses.replace(cfg, losses=dataclasses.replace(cfg.losses, occ_pos_weight=occ_pos_weight))
    if zeta is not None:
        if zeta < 0:
            raise MsdnetError("--zeta", f"must be >= 0, got {zeta}")
        cfg = dataclasses.replace(cfg, losses=dataclasses.replace(cfg.losses, zeta=zeta))
    if full_scale_rate is not None:
        if not 0 < full_scale_rate <= 1:
            raise MsdnetError("--full-scale-rate", f"must be in (0, 1], got {full_scale_rate}")
        losses = dataclasses.replace(cfg.losses, full_scale_rate=full_scale_rate)
        cfg = dataclasses.replace(cfg, losses=losses)
    if lambdas is not None:
        try:
            weights = tuple(float(v) for v in lambdas.split(","))
        except ValueError:
            weights = ()
        if len(weights) != 4 or any(v < 0 for v in weights):
            raise MsdnetError("--lambdas", f"expected four numbers >= 0 like 1,0.01,5,10, got {lambdas!r}")
        cfg = replace(cfg, losses=replace(cfg.losses, lambdas=weights))
    if start_step is not None:
        if not 0 < start_step <= cfg.diffusion.num_train_steps:
            top = cfg.diffusion.num_train_steps
            raise MsdnetError("--start-step", f"must be in 1..{top}, got {start_step}")
        cfg = replace(cfg, diffusion=replace(cfg.diffusion, start_step=start_step))
    if adapter_align is not None:
        if adapter_align < 0:
            raise MsdnetError("--adapter-align", f"must be >= 0, got {adapter_align}")
        cfg = replace(cfg, losses=replace(cfg.losses, adapter_align=adapter_align))
    if cond_align is not None:
        if cond_align < 0 or kind != "r2ldm":
            raise MsdnetError("--cond-align", f"is an R2LDM weight >= 0, got {cond_align} for {kind}")
        cfg = replace(cfg, losses=replace(cfg.losses, r2ldm_cond_align=cond_align))
    if cond_dropout is not None:
        if not 0 <= cond_dropout < 1 or kind != "r2ldm":
            raise MsdnetError("--cond-dropout", f"is an R2LDM share in [0, 1), got {cond_dropout} for {kind}")
        cfg = replace(cfg, r2ldm_cond_dropout=cond_dropout)
    cfg = _student_options(cfg, kind, denoiser_grad, denoiser_hidden, time_embed)
    if head_kind is not None:
        cfg = replace(cfg, head_kind=_choice(head_kind, HEAD_KINDS, "head"))
    if loop_steps is not None:
        if kind != "student" or not 1 <= loop_steps <= cfg.diffusion.start_step:
            raise MsdnetError("--loop-steps", f"is a student's T_m in 1..m ({cfg.diffusion.start_step})")
        cfg = replace(
            cfg, train_sample_steps=loop_steps, diffusion=replace(cfg.diffusion, sample_steps=loop_steps)
        )
    if init is not None and read_checkpoint(init)[2].recovered_from and not (head_only or distill_steps):
        raise MsdnetError(
            init,
            "was read back from an exported model (no teacher LiDAR branch): --distill or --head-only only",
        )
    if tcfg.distill_steps:
        cfg = _distill_config(init if init is not None else out / "last", cfg.train_sample_steps, tcfg)
    for name in ablate:
        if kind != "student":
            raise MsdnetError("--ablate", "ablations are of the student (MSDNet) only")
        cfg = dataclasses.replace(cfg, **{ABLATIONS[_choice(name, tuple(ABLATIONS), "ablation")]: False})
    if kind == "teacher" and teacher is not None:
        raise MsdnetError(teacher, "--teacher is for student and r2ldm runs only")
    if init is not None and (resume or (teacher is not None and kind == "teacher")):
        raise MsdnetError(init, "--init starts a new run from a checkpoint: not with --resume")
    if kind != "teacher" and teacher is None and not resume and init is None:
        raise MsdnetError(None, f"{kind} needs --teacher CKPT (a trained teacher checkpoint)")
    train_set, val_set = make_splits(
        dataset, data, cfg, val_fraction, max_frames, radar_frames, holdout, tcfg.augment, tcfg.seed
    )
    # On resume the student / R2LDM checkpoint holds its teacher: no teacher file needed.
    teacher_model = _teacher(teacher, cfg) if teacher is not None and not resume else None
    if kind != "teacher" and cfg.r2ldm_recipe != "published":  # the published latent is tanh-bounded
        cfg = _with_latent_norm(cfg, out, resume, init, teacher_model, train_set, latent_frames)

    info = init_distributed(torch.device(device))
    # Float reductions depend on the thread count: set it explicitly, never inherit it.
    torch.set_num_threads(threads or max(1, (os.cpu_count() or 1) // info.world_size))
    if device == "cuda" and info.distributed:
        device = f"cuda:{info.local_rank}"  # one GPU per process
    spec = RunSpec(
        kind=kind,
        out=out,
        epochs=n_epochs,
        resume=resume,
        save_every=save_every,
        metric_frames=metric_frames,
        device=device,
        teacher=str(teacher.resolve()) if teacher is not None else None,
        init=str(init.resolve()) if init is not None else None,
        dataset={
            "name": dataset,
            "root": str(Path(data).resolve()),
            "radar_frames": radar_frames,
            "train_frames": [train_set.frame_ids[0], train_set.frame_ids[-1], len(train_set)],
            "val_frames": [val_set.frame_ids[0], val_set.frame_ids[-1], len(val_set)],
            # val_frames is the selection slice of the training range when holdout > 0
            "holdout": holdout,
            "val_fraction": val_fraction,
        },
    )
    try:
        _run(spec, cfg, tcfg, train_set, val_set, teacher_model, info, publish)
    finally:
        shutdown_distributed()


def _with_latent_norm(
    cfg: ModelConfig,
    out: Path,
    resume: bool,
    init: Path | None,
    teacher: torch.nn.Module | None,
    train_set: PairDataset,
    frames: int,
) -> ModelConfig:
    """``cfg`` with ``latent_norm``: measured on ``frames`` training frames with a fresh teacher,
    or what the checkpoint being resumed / started from recorded (training/models/latent.py)."""
    if teacher is None or init is not None:  # --init --teacher: the student keeps its own norm
        path = out / "last" if resume else init
        return replace(cfg, latent_norm=read_checkpoint(path)[1].latent_norm) if path else cfg
    from msdnet.training.models.latent import measure_latent_norm

    if frames < 1:
        raise MsdnetError("--latent-frames", f"must be >= 1, got {frames}")
    norm = measure_latent_norm(teacher, train_set, cfg, frames)
    scales = [s for _, s in norm]
    click.echo(
        f"latent norm on {min(frames, len(train_set))} training frames: shift mean "
        f"{sum(m for m, _ in norm) / len(norm):.3f}, scale {min(scales):.3f}-{max(scales):.3f}"
    )
    return replace(cfg, latent_norm=norm)


def _distill_config(path: Path, steps: int, tcfg: TrainConfig) -> ModelConfig:
    """The config of a ``--distill N --loop-steps K`` run: the checkpoint's, its T_m set to K < N."""
    icfg = read_checkpoint(path)[1]
    if not icfg.use_dgfd:
        raise MsdnetError(path, "has no DGFD loop to distil (trained with --ablate dgfd)")
    if not 1 <= steps < tcfg.distill_steps <= icfg.diffusion.start_step:
        top = icfg.diffusion.start_step
        got = f"got {steps} and {tcfg.distill_steps}"
        raise MsdnetError("--distill", f"needs 1 <= --loop-steps < N <= m ({top}), {got}")
    return replace(icfg, train_sample_steps=steps, diffusion=replace(icfg.diffusion, sample_steps=steps))


def _init_model(
    path: Path, kind: str, cfg: ModelConfig, teacher: torch.nn.Module | None, distill: bool = False
) -> torch.nn.Module:
    """The model of checkpoint ``path`` (weights, and the teacher a student / R2LDM holds), after
    checking it is a ``kind`` of the same config. Two exceptions: a new ``head_kind`` (the
    tensors whose names and shapes match are taken, the rest start fresh), and a student / R2LDM
    given ``teacher`` (``--teacher``: its own weights from ``path``, the frozen teacher from there)."""
    folder, icfg, istate = read_checkpoint(path)
    if istate.kind != kind:
        raise MsdnetError(folder, f"--init is a {istate.kind} checkpoint, this run trains a {kind}")
    loop = ("train_sample_steps", "diffusion") if distill else ()  # --distill sets a new T_m
    differs = config_diff(icfg, cfg, ignore=("head_kind", *loop))
    if differs:
        raise MsdnetError(folder, f"--init config differs from this run: {', '.join(differs)}"[:300])
    if kind != "teacher" and teacher is None and icfg.head_kind != cfg.head_kind:
        raise MsdnetError(folder, f"the head is the teacher's: --head {cfg.head_kind} needs --teacher")
    old = load_checkpoint(folder)[0]
    if teacher is None and icfg.head_kind == cfg.head_kind and not distill:
        return old  # (--distill: rebuilt below, so the loop runs the run's T_m, not --init's)
    model = build_model(kind, cfg, teacher=teacher)
    dst = model.state_dict()
    take = {
        k: v
        for k, v in old.state_dict().items()
        if k in dst and dst[k].shape == v.shape and not (teacher is not None and k.startswith("teacher."))
    }
    model.load_state_dict(take, strict=False)
    fresh = sorted({k.rsplit(".", 2)[0] for k in dst if k not in take and not k.startswith("teacher.")})
    click.echo(
        f"--init: {len(take)} of {len(dst)} tensors from {folder}; fresh: {', '.join(fresh) or 'none'}"
    )
    return model


def _run(
    spec: RunSpec,
    cfg: ModelConfig,
    tcfg: TrainConfig,
    train_set: PairDataset,
    val_set: PairDataset,
    teacher: torch.nn.Module | None,
    info: DistInfo,
    publish: Path | None = None,
) -> None:
    """Build the model (same seed on every rank), train it, print one summary line; a finished
    run's best/ is copied to ``publish`` as weights only."""
    torch.manual_seed(tcfg.seed)
    if spec.init is not None:
        model = _init_model(Path(spec.init), spec.kind, cfg, teacher, distill=tcfg.distill_steps > 0)
    else:
        model = build_model(spec.kind, cfg, teacher=teacher)
    if tcfg.head_only and spec.kind == "teacher":  # the students' distillation target stays
        model.encoder.requires_grad_(False)
        model.s2d.requires_grad_(False)
    elif tcfg.head_only:  # a student: its head copy alone, on its own F_r^D (Eq. 7 only)
        model.requires_grad_(False)
        model.teacher.head.requires_grad_(True)
        model.head_only = True
    if tcfg.distill_steps:  # the loop of the --init checkpoint (on resume: read again), frozen
        if spec.init is not None:  # the model holds --init's weights now
            source_step = copy.deepcopy(model.step)
        else:
            source_step = load_checkpoint(Path(read_checkpoint(spec.out / "last")[2].init))[0].step
        model.requires_grad_(False)
        model.step.requires_grad_(True)
        model.enable_distillation(source_step, tcfg.distill_steps, tcfg.distill_head)
    metrics = partial(occupancy_counts, modality="lidar" if spec.kind == "teacher" else "radar")
    state = train(model, cfg, tcfg, train_set, val_set, spec, partial(collate, cfg=cfg), info, metrics)
    if info.is_main:
        val = state.history[-1]["val_loss"] if state.history else float("nan")
        best = state.best_val_loss if state.best_val_loss is not None else float("nan")
        click.echo(
            f"{spec.kind}: epoch {state.epoch}/{spec.epochs}, step {state.step}, val loss {val:.4g}, "
            f"best {best:.4g} -> {spec.out / 'best'}"
        )
        if publish is not None and state.epoch >= spec.epochs and (spec.out / "best").exists():
            folder, digest = publish_checkpoint(spec.out / "best", publish)
            click.echo(f"published {spec.out / 'best'} -> {folder} (model.safetensors sha256 {digest[:16]})")


if __name__ == "__main__":
    main()
