"""Model and training configs: frozen dataclasses, one comment per field; presets by name.

The manifest written at export is ``dataclasses.asdict(ModelConfig)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from msdnet.runtime.spec.ddim import DiffusionConfig
from msdnet.runtime.spec.grid import GRID_PRESETS, GridConfig
from msdnet.training.published_config import PublishedR2LDMConfig


@dataclass(frozen=True)
class LossWeights:
    """Loss weights (MSDNet Sec. IV-B)."""

    rho: float = 1.0  # occupancy weight per scale, Eq. 7
    zeta: float = 10.0  # offset weight per scale, Eq. 7
    alpha: float = 10.0  # non-empty BEV cells, Eq. 8 and 14
    gamma: float = 20.0  # empty BEV cells, Eq. 8 and 14
    # Eq. 15 weights of: recon, reconstruction distillation, diffusion distillation, diffusion
    lambdas: tuple[float, float, float, float] = (1.0, 0.01, 5.0, 10.0)
    # weight of occupied voxels in Eq. 5 (1 = the paper); sparse LiDAR needs more, see docs/training.md
    occ_pos_weight: float = 1.0
    # share of the half-scale voxels far from every LiDAR point (under an empty quarter-scale voxel)
    # whose full-scale children enter Eq. 5-6 in a training step, weighted 1 / share so that the
    # loss is unbiased; the rest of the full scale is not computed (training/models/full_rows.py).
    # 1 = every voxel, the exact loss; validation always scores every voxel
    full_scale_rate: float = 1.0
    # let Eq. 14 and the reconstruction loss reach the denoiser's weights through the DDIM loop
    # (False: the denoiser learns Eq. 10 only; the loop's gradients still reach RGFD and the
    # adapter). Measured: with it on, Eq. 14 is 120-640x Eq. 10 on the denoiser and the
    # denoiser stops predicting noise (docs/training.md).
    denoiser_distill_grad: bool = False
    # with denoiser_distill_grad: the loop's gradient reaches the denoiser's weights through its
    # last N DDIM steps only (truncated back-propagation; 0 = every step, Eq. 15 as the paper)
    denoiser_grad_steps: int = 0
    # with denoiser_distill_grad: per-loss gradient normalisation, the loop's gradient on the
    # denoiser's weights scaled to this multiple of Eq. 10's (0 = unscaled; training/nn/grad_balance.py)
    denoiser_grad_ratio: float = 0.0
    # weight of the adapter's alignment loss: x_m (Eq. 12) against the forward chain at m of the
    # teacher latent with the same eps, sqrt(abar_m) F_l + sqrt(1 - abar_m) eps (Eq. 9). When > 0
    # the gate learns from it alone (it is detached in the loop); 0 = the gate learns end to end
    # through Eq. 14, where it measurably collapses to delta = 1 (no noise; docs/training.md)
    adapter_align: float = 1.0
    # R2LDM only: weight of an auxiliary regression of the normalised teacher latent from the
    # radar condition F_r^S (a 1x1 conv head, training only). The U-Net alone gives the radar
    # encoder no signal until it uses the condition, and a fresh condition is noise it learns to
    # ignore; 0 = R2LDM as published (the encoder learns through the eps loss only)
    r2ldm_cond_align: float = 0.0


@dataclass(frozen=True)
class ModelConfig:
    """Everything that fixes the architecture; weights are meaningless without it."""

    preset: str  # name of the preset this came from
    grid: GridConfig  # voxel grid (radar frame)
    # radar point columns fed to the VFE, in order
    radar_columns: tuple[str, ...] = ("x", "y", "z", "rcs", "v_r_compensated")
    lidar_columns: tuple[str, ...] = ("x", "y", "z")  # LiDAR point columns fed to the teacher's VFE
    max_voxels_radar: int = 4096  # voxel cap for radar clouds
    max_voxels_lidar: int = 60000  # voxel cap for LiDAR clouds
    vfe_channels: int = 16  # per-voxel MLP width
    encoder_channels: tuple[int, int, int, int] = (16, 32, 64, 64)  # backbone width at 1, 1/2, 1/4, 1/8
    bev_channels: int = 64  # C of every BEV map: F^S, F^R, F^D (1, C, H/8, W/8)
    s2d_channels: int = 64  # teacher feature-enhancement width
    rgfd_channels: int = 64  # RGFD width after the first Down block (doubles after the second)
    adapter_hidden: int = 64  # noise-adapter bottleneck / MLP width
    denoiser_hidden: int = 32  # light denoiser bottleneck width (1x1 -> 3x3 -> 1x1)
    time_embed_dim: int = 64  # sinusoidal time embedding width
    head_channels: tuple[int, int, int] = (32, 16, 8)  # recon head 3D width at 1/4, 1/2, 1
    # recon head (training.nn.heads): "dense" (3x3x3 convs and volume GroupNorms down to 1/2),
    # "sparse" (only 1/8 and 1/4 mix neighbours, per voxel below: runs on occupied voxels only;
    # nn/head_sparse.py; not the default, see docs/training.md) or "gated" (dense with a
    # fixed-statistics norm at 1/2, whose coarse-to-fine graph computes 1/2 only under the 1/4 voxels
    # above the gate; nn/head_gated.py, made from a dense student by training/recipe/gated_head.py)
    head_kind: str = "dense"
    # sparse head only: widths at 1/4 and 1/2 (1/8 and the full scale keep head_channels[0], [2]);
    # wider than the dense head's, since below 1/4 a voxel sees only its parent (head_sparse.py)
    head_sparse_widths: tuple[int, int] = (64, 32)
    r2ldm_channels: tuple[int, ...] = (128, 64)  # R2LDM U-Net widths per level, the first >= 2C
    r2ldm_cond_channels: int = 32  # R2LDM condition channels concatenated into every U-Net block
    # R2LDM sampling clips its x0 estimate to +-this (unit-variance latents; <= 0: no clip)
    r2ldm_x0_clip: float = 8.0
    # R2LDM classifier-free guidance: training zeroes the condition of this share of frames, and
    # the step graph mixes eps = eps(0) + w (eps(c) - eps(0)) with w = r2ldm_guidance (1 = off)
    r2ldm_cond_dropout: float = 0.0
    r2ldm_guidance: float = 1.0
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)  # schedule, m, T_m
    train_sample_steps: int = 5  # DDIM steps of the student's training loop (with grads)
    r2ldm_sample_steps: int = 128  # R2LDM sampling steps from pure noise
    # R2LDM recipe: "improved" (ours, the fields above) or "published" (the authors' code: the
    # teacher is its own LPCR autoencoder, and ``published`` holds the rest;
    # training/models/r2ldm_published.py)
    r2ldm_recipe: str = "improved"
    published: PublishedR2LDMConfig = field(default_factory=PublishedR2LDMConfig)  # recipe "published"
    threshold: float = 0.5  # occupancy threshold for decoding points
    losses: LossWeights = field(default_factory=LossWeights)  # loss weights
    # (shift, scale) per radar column: the encoder graph applies (mean - shift) / scale to the
    # per-voxel column means, so the runtime feeds raw means; () -> defaults by column name
    radar_feature_norm: tuple[tuple[float, float], ...] = ()
    lidar_feature_norm: tuple[tuple[float, float], ...] = ()  # the same for the LiDAR columns
    # (shift, scale) per BEV channel of the teacher's F_l^D, measured on training frames when the
    # student / R2LDM run starts (training/models/latent.py); diffusion works on (F - shift) / scale and
    # the exported head de-normalises. () = identity (checkpoints without a measured norm)
    latent_norm: tuple[tuple[float, float], ...] = ()
    use_rgfd: bool = True  # ablation switch: False = F_r^R is the encoder's F_r^S (no RGFD)
    use_dgfd: bool = (
        True  # ablation switch: False = no adapter, no loop: F_r^D = F_r^R (exports an identity loop)
    )
    # ablation switch: False = no noise adapter, x_m is Eq. 9 at m: sqrt(abar_m) F + sqrt(1 - abar_m) eps
    use_adapter: bool = True
    s2d_blocks: int = 2  # residual blocks per resolution in the teacher's S2D enhancement
    occupancy_prior: float = 0.02  # initial occupancy probability of the head (its bias init)

    def __post_init__(self) -> None:
        # Fill the default normalisation once, so asdict() / the manifest carry explicit numbers.
        for name, cols in (("radar", self.radar_columns), ("lidar", self.lidar_columns)):
            attr = f"{name}_feature_norm"
            norm = getattr(self, attr)
            if not norm:
                norm = default_feature_norm(cols, self.grid)
            norm = tuple((float(a), float(b)) for a, b in norm)
            if len(norm) != len(cols) or any(b <= 0 for _, b in norm):
                raise ValueError(f"{attr} needs one (shift, scale > 0) per column of {cols}")
            object.__setattr__(self, attr, norm)
        latent = tuple((float(a), float(b)) for a, b in self.latent_norm)
        if latent and (len(latent) != self.bev_channels or any(b <= 0 for _, b in latent)):
            need = f"() or one (shift, scale > 0) per BEV channel ({self.bev_channels})"
            raise ValueError(f"latent_norm needs {need}")
        object.__setattr__(self, "latent_norm", latent)


# Typical spread of the non-geometric point columns: (shift, scale) so that most values land
# in [-1, 1] (VoD RCS in dBsm: -30 ... +8; radial velocities in m/s; Astyx magnitude ~45-65).
COLUMN_NORMS: dict[str, tuple[float, float]] = {
    "rcs": (-10.0, 20.0),
    "v_r": (0.0, 5.0),
    "v_r_compensated": (0.0, 5.0),
    "mag": (50.0, 10.0),
    "time": (0.0, 0.1),
    "intensity": (0.5, 0.5),
    "reflectance": (0.5, 0.5),
}


def default_feature_norm(columns: tuple[str, ...], grid: GridConfig) -> tuple[tuple[float, float], ...]:
    """(shift, scale) per column: x, y, z map the grid range onto [-1, 1]; others COLUMN_NORMS
    (unknown names: identity)."""
    lo, hi = grid.point_range[:3], grid.point_range[3:]
    geo = {a: ((lo[i] + hi[i]) / 2.0, (hi[i] - lo[i]) / 2.0) for i, a in enumerate("xyz")}
    return tuple(geo.get(c, COLUMN_NORMS.get(c, (0.0, 1.0))) for c in columns)


@dataclass(frozen=True)
class AugmentConfig:
    """Ranges of the random transforms (all off: ``AugmentConfig.off()``)."""

    mirror_p: float = 0.5  # probability of mirroring y
    yaw_deg: float = 10.0  # largest yaw, degrees (either way)
    scale: float = 0.05  # largest relative scale change of x, y, z
    dropout_p: float = 0.5  # probability that a frame's radar points are thinned
    keep_min: float = 0.4  # lowest share of radar points kept by a thinned frame

    @staticmethod
    def off() -> AugmentConfig:
        """No augmentation (the identity)."""
        return AugmentConfig(mirror_p=0.0, yaw_deg=0.0, scale=0.0, dropout_p=0.0, keep_min=1.0)

    @property
    def enabled(self) -> bool:
        """True when any transform can change a frame."""
        return self != AugmentConfig.off()


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (papers: Adam, lr 1e-3, OneCycleLR, batch 4)."""

    epochs_teacher: int = 60  # teacher epochs
    epochs_student: int = 90  # student / R2LDM epochs
    batch_size: int = 4  # frames per step (per process under torchrun)
    lr: float = 1e-3  # peak learning rate of OneCycleLR
    weight_decay: float = 0.0  # Adam weight decay
    grad_clip: float = 10.0  # max gradient norm
    num_workers: int = 0  # DataLoader workers
    seed: int = 0  # seed for weights, shuffling and noise
    # decay of an exponential moving average of the trainable weights, updated every step
    # (0 = off; the official R2LDM code evaluates an EMA at 0.995). When on, validation scores
    # the EMA weights and best/ holds them; last/ keeps the raw weights and the EMA for resume
    ema_decay: float = 0.0
    # train the reconstruction head alone: a teacher's on the LiDAR encoder and S2D --init left
    # (the students' distillation target is unchanged); a student's (the teacher copy it holds) on
    # its own F_r^D with Eq. 7, everything else frozen
    head_only: bool = False
    # few-step distillation of a student's loop (--distill N): its denoiser alone learns to reach,
    # in the config's T_m steps, the F_r^D a frozen copy of the --init loop reaches in N (0 = off)
    distill_steps: int = 0
    # --distill-head W: add W x the MSE of the full-scale occupancy the frozen head decodes from
    # both loops' F_r^D (what the threshold sees), beside the latent MSE
    distill_head: float = 0.0
    augment: AugmentConfig = field(default_factory=AugmentConfig)  # training-frame transforms


# Peak learning rate of R2LDM's stage 2 unless --lr says otherwise: the R2LDM paper trains it at
# 1e-4; at the preset's 1e-3 the U-Net can collapse to predicting zero at the OneCycleLR peak and
# not recover (docs/training.md). OneCycleLR warms up over its first 30 %.
R2LDM_LR = 2e-4

# The student's start step m: 100, not the paper's 500. With unit-variance latents and the gate
# aligned to the forward chain at m, m = 500 leaves x_m nearly pure noise and the student learns
# far less than at m = 100 (docs/training.md). T_m = 50 steps either way (interval n = m / T_m = 2).
STUDENT_DIFFUSION = DiffusionConfig(start_step=100)


def _preset(name: str, **kw: object) -> ModelConfig:
    base = ModelConfig(preset=name, grid=GRID_PRESETS[name], diffusion=STUDENT_DIFFUSION)
    return replace(base, **kw)  # type: ignore[arg-type]


MODEL_PRESETS: dict[str, ModelConfig] = {
    "tiny": _preset(
        "tiny",
        max_voxels_radar=1024,
        max_voxels_lidar=8192,
        vfe_channels=8,
        encoder_channels=(8, 16, 16, 16),
        bev_channels=16,
        s2d_channels=16,
        rgfd_channels=16,
        adapter_hidden=16,
        denoiser_hidden=8,
        time_embed_dim=16,
        head_channels=(8, 8, 8),
        head_sparse_widths=(8, 8),
        r2ldm_channels=(32, 32),
        r2ldm_cond_channels=8,
        train_sample_steps=2,
        r2ldm_sample_steps=8,
    ),
    # R2LDM's U-Net at (128, 64): input / output width 2C, R2LDM / MSDNet 2.95 M / 1.19 M = 2.5
    # (the paper: 40.3 M / 20.5 M = 2.0; at (128, 128) it would be 4.2).
    # 50 training loop steps, as inference: the light denoiser costs ~0.4 s of a ~1 s step
    "lite": _preset("lite", max_voxels_lidar=40000, r2ldm_channels=(128, 64), train_sample_steps=50),
    "paper": _preset(
        "paper",
        max_voxels_lidar=120000,
        encoder_channels=(16, 32, 64, 128),
        bev_channels=128,
        s2d_channels=128,
        rgfd_channels=128,
        adapter_hidden=128,
        denoiser_hidden=64,
        time_embed_dim=128,
        head_channels=(32, 8, 8),  # 1/2 and full scale kept narrow: 40x320x320 on a CPU
        head_sparse_widths=(32, 16),  # 1/4 is 64,000 voxels on the paper grid: kept at c4
        r2ldm_channels=(256, 256, 464),  # U-Net 38.1 M, R2LDM 39.1 M (the paper: 40.3 M)
        r2ldm_cond_channels=64,
    ),
}

# Table IV like for like (timed with random weights; not trained): the paper preset widened to
# the paper's sizes: MSDNet 20.1 M deployed parameters (the paper: 20.5 M), R2LDM 40.2 M (40.3 M).
MODEL_PRESETS["paper-width"] = replace(
    MODEL_PRESETS["paper"],
    preset="paper-width",
    encoder_channels=(32, 64, 128, 128),
    rgfd_channels=368,
    adapter_hidden=352,
    denoiser_hidden=192,
    head_channels=(64, 16, 8),
    head_sparse_widths=(64, 16),
)

TRAIN_PRESETS: dict[str, TrainConfig] = {
    "tiny": TrainConfig(epochs_teacher=2, epochs_student=2, batch_size=2),
    "lite": TrainConfig(epochs_teacher=12, epochs_student=12),
    "paper": TrainConfig(),
    "paper-width": TrainConfig(),
}
