"""R2LDM as its authors published it (``--recipe published``): both stages, and the sampler in torch.

Read from the public code (github.com/NathanDrake67/R2LDM: ``scn.py``, ``rpn.py``,
``continuous_time.py``, ``base.py``, ``efficient_unet.py``) and written anew on our sparse layers:

- **Latent** (:class:`QuarterEncoder`): a sparse encoder with two stride-2 layers (1/4 of the grid),
  its level-2 voxels scattered into a dense volume, collapsed over height by a bias-free 1x1 conv
  and a ReLU to ``latent_channels`` (8), then ``z = 2 tanh(f) - 1``: in [-1, 1) and exactly -1 in
  cells without a voxel (published: ``normalize(clamp(tanh(f), 0, 1))`` with f >= 0 after ReLU).
  LiDAR and radar have one each (x, y, z columns only).
- **Stage 1** (:class:`LPCRAutoencoder`, trained as ``teacher``): LiDAR latent -> the LPCR decoder
  (:class:`LPCRDecoder`: ``(z + 1) / 2``, 3x3 stride-2 conv to 1/8, our S2D hourglass, our
  reconstruction head) -> full-scale occupancy and offsets. Loss: BCE + 0.04 * L1(offset) at full
  scale, the L1 a mean over the occupied voxels' coordinates (published ``F.l1_loss``).
- **Stage 2** (:class:`PublishedR2LDM`, trained as ``r2ldm``): the stage-1 model frozen; the radar
  latent is the condition, concatenated at the U-Net input only (``training/nn/unet_published.py``).
  eps-prediction on the LiDAR latent with t ~ U(0, 1), the cosine log-SNR schedule and min-SNR-5
  weights (``runtime/spec/cosine_logsnr.py``).
- **Sampling**: DDIM eta = 0 with x0 clipped to +-1, each step re-noised and repeated (RePaint
  style); :meth:`PublishedR2LDM.predict` is the torch reference of the runtime's loop.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from msdnet.runtime.engine.rulebook import level_shapes
from msdnet.runtime.spec.cosine_logsnr import sampler_plan
from msdnet.training.config import ModelConfig
from msdnet.training.data.batch import Batch, EncoderInput
from msdnet.training.models.losses import occupancy_bce
from msdnet.training.nn.blocks import group_norm
from msdnet.training.nn.heads import build_head
from msdnet.training.nn.s2d import S2D
from msdnet.training.nn.sparse import SparseConvBlock
from msdnet.training.nn.unet import ddim_update_clipped
from msdnet.training.nn.unet_published import PublishedUNet

LEVELS = 2  # stride-2 layers of the published latent: 1/4 of the grid


def latent_shape(cfg: ModelConfig) -> tuple[int, int, int]:
    """(L, H4, W4) of the published latent (and of every sampler buffer)."""
    _, h4, w4 = level_shapes(cfg.grid)[LEVELS]
    return cfg.published.latent_channels, h4, w4


class QuarterEncoder(nn.Module):
    """Voxels + rulebooks of levels 0..2 -> latent z (B, L, H4, W4) in [-1, 1), empty cells -1."""

    def __init__(self, cfg: ModelConfig, modality: str) -> None:
        super().__init__()
        norm = cfg.radar_feature_norm if modality == "radar" else cfg.lidar_feature_norm
        shift, scale = zip(*norm, strict=True)
        self.register_buffer("shift", torch.tensor(shift, dtype=torch.float32), persistent=False)
        self.register_buffer("scale", torch.tensor(scale, dtype=torch.float32), persistent=False)
        ch = cfg.published.encoder_channels
        vfe = cfg.vfe_channels
        self.vfe = nn.Sequential(nn.Linear(len(norm), vfe), nn.LayerNorm(vfe), nn.ReLU())
        self.subm = nn.ModuleList([SparseConvBlock(cfg.vfe_channels, ch[0])])
        self.down = nn.ModuleList()
        for level in range(1, LEVELS + 1):
            self.down.append(SparseConvBlock(ch[level - 1], ch[level], down=True))
            self.subm.append(SparseConvBlock(ch[level], ch[level]))
        self.shape4 = level_shapes(cfg.grid)[LEVELS]  # (D4, H4, W4)
        # bias-free, so that a cell without voxels stays exactly 0 (z = -1)
        self.collapse = nn.Conv2d(ch[-1] * self.shape4[0], cfg.published.latent_channels, 1, bias=False)

    def forward(
        self,
        voxel_features: Tensor,
        subm_rules_0: Tensor,
        down_rules_1: Tensor,
        subm_rules_1: Tensor,
        down_rules_2: Tensor,
        subm_rules_2: Tensor,
        bev_coords: Tensor,
    ) -> Tensor:
        """One frame (``runtime.model.onnx_spec.ENCODER_QUARTER``): bev_coords (V_2, 4) [b = 0, z, y, x]
        -> z (1, L, H4, W4)."""
        rules = (subm_rules_0, down_rules_1, subm_rules_1, down_rules_2, subm_rules_2)
        return self.run(voxel_features, rules, bev_coords, 1)

    def run(self, feats: Tensor, rules: tuple[Tensor, ...], coords: Tensor, batch_size: int) -> Tensor:
        """feats (V_0, F) raw column means; rules as :meth:`forward`; coords (V_2, 4) -> (B, L, H4, W4)."""
        x = self.subm[0](self.vfe((feats - self.shift) / self.scale), rules[0])
        for level in range(LEVELS):
            x = self.subm[level + 1](self.down[level](x, rules[1 + 2 * level]), rules[2 + 2 * level])
        d4, h4, w4 = self.shape4
        c = x.shape[1]
        lin = ((coords[:, 0] * d4 + coords[:, 1]) * h4 + coords[:, 2]) * w4 + coords[:, 3]
        dense = x.new_zeros(batch_size * d4 * h4 * w4, c).index_put((lin,), x)
        dense = dense.reshape(batch_size, d4, h4, w4, c).permute(0, 4, 1, 2, 3)  # (B, c, D4, H4, W4)
        dense = dense.reshape(batch_size, c * d4, h4, w4)  # channel-major height collapse
        return 2.0 * torch.tanh(torch.relu(self.collapse(dense))) - 1.0

    def encode(self, inp: EncoderInput) -> Tensor:
        """z (B, L, H4, W4) of a collated :class:`EncoderInput`."""
        rules = (inp.subm[0], inp.down[0], inp.subm[1], inp.down[1], inp.subm[2])
        return self.run(inp.features, rules, inp.level_coords[LEVELS], inp.batch_size)


class LPCRDecoder(nn.Module):
    """Latent z (B, L, H4, W4) in [-1, 1] -> the reconstruction head's outputs (clamped to +-1 first)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c = cfg.bev_channels
        self.to8 = nn.Sequential(
            nn.Conv2d(cfg.published.latent_channels, c, 3, stride=2, padding=1), group_norm(c), nn.GELU()
        )
        self.s2d = S2D(cfg)
        self.head = build_head(cfg)

    def features(self, z: Tensor) -> Tensor:
        """z -> dense BEV features (B, C, H8, W8) for the head."""
        return self.s2d(self.to8((z.clamp(-1.0, 1.0) + 1.0) * 0.5))

    def multi_scale(self, z: Tensor) -> list[tuple[Tensor, Tensor]]:
        """As ``ReconHead.multi_scale`` (logits and offsets at 1/4, 1/2, 1)."""
        return self.head.multi_scale(self.features(z))

    def packed(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """As ``ReconHead.packed`` (``recon_head.onnx``)."""
        return self.head.packed(self.features(z))

    def sparse(self, z: Tensor, gate: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """As ``ReconHead.sparse`` (``recon_head_sparse.onnx``)."""
        return self.head.sparse(self.features(z), gate)

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """z -> (occupancy (B, 1, D, H, W), offsets (B, 3, D, H, W))."""
        return self.head(self.features(z))


def lpcr_loss(preds: list[tuple[Tensor, Tensor]], batch: Batch, cfg: ModelConfig) -> dict[str, Tensor]:
    """Stage 1 at full scale: BCE(occupancy) + w * mean |offset error| over occupied voxels' coordinates."""
    logits, off = preds[-1]
    occ_t, off_t = batch.targets[-1]
    bce = occupancy_bce(logits.squeeze(1), occ_t, cfg.losses.occ_pos_weight)
    mask = occ_t.unsqueeze(1).expand_as(off)  # (B, 3, D, H, W)
    l1 = ((off - off_t).abs() * mask).sum() / mask.sum().clamp_min(1.0)
    return {"loss": bce + cfg.published.offset_weight * l1, "occ_s1": bce, "off_s1": l1}


class LPCRAutoencoder(nn.Module):
    """Stage 1: LiDAR -> latent -> LPCR decoder. ``features`` is the latent stage 2 learns."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = QuarterEncoder(cfg, "lidar")
        self.decoder = LPCRDecoder(cfg)

    def features(self, lidar: EncoderInput) -> Tensor:
        """z_l (B, L, H4, W4)."""
        return self.encoder.encode(lidar)

    def losses(self, batch: Batch) -> dict[str, Tensor]:
        """{"loss", "occ_s1", "off_s1"} (:func:`lpcr_loss`)."""
        return lpcr_loss(self.decoder.multi_scale(self.features(batch.lidar)), batch, self.cfg)

    def predict(self, inp: EncoderInput, noise: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """LiDAR input -> (occupancy (B, D, H, W), offsets (B, 3, D, H, W)); ``noise`` unused."""
        occ, off = self.decoder(self.features(inp))
        return occ.squeeze(1), off


class PublishedStep(nn.Module):
    """``r2ldm_step.onnx`` of the published recipe: (x_t, cond, lambda_t, abar_t, abar_s) -> x_s,
    DDIM eta = 0 with the x0 clip (``runtime/spec/cosine_logsnr.py`` step 4)."""

    def __init__(self, unet: PublishedUNet, x0_clip: float) -> None:
        super().__init__()
        self.unet = unet
        self.x0_clip = float(x0_clip)

    def forward(self, x_t: Tensor, cond: Tensor, t: Tensor, abar_t: Tensor, abar_prev: Tensor) -> Tensor:
        return ddim_update_clipped(x_t, self.unet(x_t, t, cond), abar_t, abar_prev, self.x0_clip)


def log_snr_torch(t: Tensor, lo: float, hi: float) -> Tensor:
    """``runtime.spec.cosine_logsnr.log_snr`` in torch: t (B,) in [0, 1] -> lambda (B,)."""
    t_min = float(np.arctan(np.exp(-0.5 * hi)))
    t_max = float(np.arctan(np.exp(-0.5 * lo)))
    return -2.0 * torch.log(torch.tan(t_min + t * (t_max - t_min)).clamp_min(1e-20))


class PublishedR2LDM(nn.Module):
    """Stage 2: radar latent condition, U-Net eps-prediction on the frozen stage 1's LiDAR latent."""

    takes_rng = True  # predict() accepts the numpy Generator of the re-noising draws

    def __init__(self, cfg: ModelConfig, teacher: LPCRAutoencoder | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = QuarterEncoder(cfg, "radar")
        self.step = PublishedStep(PublishedUNet(cfg.published), cfg.published.x0_clip)
        teacher = LPCRAutoencoder(cfg) if teacher is None else teacher
        teacher.requires_grad_(False)
        self.teacher = teacher.eval()

    def train(self, mode: bool = True) -> PublishedR2LDM:
        super().train(mode)
        self.teacher.eval()
        return self

    @property
    def head(self) -> LPCRDecoder:
        """The frozen LPCR decoder (``recon_head.onnx``)."""
        return self.teacher.decoder

    @property
    def unet(self) -> PublishedUNet:
        return self.step.unet

    def losses(self, batch: Batch) -> dict[str, Tensor]:
        """{"loss" = "diff": min-SNR-weighted eps L2}; outside training also "diff_shuffled" (another
        frame's condition, or the own one mirrored for a batch of one)."""
        p = self.cfg.published
        with torch.no_grad():
            x0 = self.teacher.features(batch.lidar)
        cond = self.encoder.encode(batch.radar)
        lam = log_snr_torch(torch.rand(x0.shape[0], device=x0.device), p.logsnr_min, p.logsnr_max)
        a2 = torch.sigmoid(lam).reshape(-1, 1, 1, 1)
        eps = torch.randn_like(x0)
        x_t = a2.sqrt() * x0 + (1.0 - a2).sqrt() * eps
        snr = lam.exp()
        weight = snr.clamp(max=p.min_snr_gamma) / snr  # (B,)

        def weighted(c: Tensor) -> Tensor:
            per = (self.unet(x_t, lam, c) - eps).pow(2).flatten(1).mean(1)  # (B,) per-sample L2
            return (per * weight).mean()

        diff = weighted(cond)
        out = {"loss": diff, "diff": diff}
        if not self.training:
            out["diff_shuffled"] = weighted(cond.roll(1, dims=0) if cond.shape[0] > 1 else cond.flip(-1))
        return out

    def sample(self, cond: Tensor, x: Tensor, steps: int, rng: np.random.Generator | None) -> Tensor:
        """The resampled DDIM loop from x_T = ``x`` (B, L, H4, W4); re-noising draws come from
        ``rng`` (numpy, as the runtime) or torch.randn."""
        plan = sampler_plan(steps, self.cfg.published.resample, self.cfg.published.logsnr_min,
                            self.cfg.published.logsnr_max)  # fmt: skip
        coeffs = torch.from_numpy(plan.coefficients)
        for k in range(coeffs.shape[0]):
            x = self.step(x, cond, coeffs[k, 0:1], coeffs[k, 1:2], coeffs[k, 2:3])
            a, b = plan.renoise[k]
            if np.isfinite(a):
                if rng is None:
                    eps = torch.randn_like(x)
                else:
                    eps = torch.from_numpy(rng.standard_normal(tuple(x.shape), dtype=np.float32))
                x = float(a) * x + float(b) * eps
        return x

    def predict(
        self,
        inp: EncoderInput,
        noise: Tensor | None = None,
        sample_steps: int | None = None,
        rng: np.random.Generator | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Radar input, x_T (B, L, H4, W4) (default torch.randn) -> full-scale (occupancy (B, D, H, W),
        offsets (B, 3, D, H, W)) after ``sample_steps`` DDIM steps (default ``published.sample_steps``)."""
        cond = self.encoder.encode(inp)
        x = torch.randn_like(cond) if noise is None else noise
        steps = self.cfg.published.sample_steps if sample_steps is None else sample_steps
        occ, off = self.head(self.sample(cond, x, steps, rng))
        return occ.squeeze(1), off


def build_published(kind: str, cfg: ModelConfig, teacher: nn.Module | None = None) -> nn.Module:
    """kind "teacher" -> :class:`LPCRAutoencoder`; "r2ldm" -> :class:`PublishedR2LDM`."""
    if kind == "teacher":
        return LPCRAutoencoder(cfg)
    if kind == "r2ldm":
        if teacher is not None and not isinstance(teacher, LPCRAutoencoder):
            raise ValueError("the published R2LDM needs a published (LPCR) stage-1 teacher")
        return PublishedR2LDM(cfg, teacher)
    raise ValueError(f"the published recipe trains 'teacher' (stage 1) and 'r2ldm' (stage 2), not {kind!r}")
