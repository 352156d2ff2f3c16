"""The three trainable models: MSDNet's teacher and student, and the R2LDM baseline.

Every model has ``losses(batch) -> {"loss": total, term: value, ...}`` (the training loop's
contract) and ``predict(inp, noise) -> (occupancy (B, D, H, W) in [0, 1], offsets (B, 3, D, H, W)
metres [dx, dy, dz])`` at full scale.

- Teacher (MSDNet III-B): LiDAR encoder -> S2D -> F_l^D -> reconstruction head; loss Eq. 7.
- Student (MSDNet III-C/D): radar encoder -> RGFD -> F_r^R -> noise adapter (Eq. 12) -> DDIM
  loop over the light denoiser (``cfg.train_sample_steps`` steps from m while training, with
  gradients; ``cfg.diffusion.sample_steps`` at inference) -> F_r^D -> the TEACHER's head (one
  set of weights shared by both branches, frozen with the teacher). The denoiser also learns
  the eps-prior on noised F_l^D (Eq. 10). Loss Eq. 15.
- R2LDM: radar encoder -> condition c = F_r^S; U-Net eps-prediction on noised F_l^D (L2);
  sampled from pure noise with ``cfg.r2ldm_sample_steps`` DDIM steps from T; the teacher's head
  decodes (R2LDM stage 1 = the teacher, stage 2 = this model).

The student and R2LDM hold the trained teacher as a frozen submodule (``requires_grad=False``,
always in eval mode), so their checkpoints carry it and ``parameters()`` with
``requires_grad`` lists only their own weights. The diffusion schedule comes from
``msdnet.runtime.spec.ddim`` (alphas_cumprod, step_coefficients); nothing is recomputed here.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor, nn
from torch.func import functional_call

from msdnet.runtime.spec.ddim import alphas_cumprod, step_coefficients
from msdnet.training.config import ModelConfig
from msdnet.training.data.batch import Batch, EncoderInput
from msdnet.training.models.latent import LatentHead, norm_tensors
from msdnet.training.models.losses import (
    eps_loss,
    feature_distillation,
    head_loss,
    student_total,
)
from msdnet.training.nn.adapter import ForwardNoising, NoiseAdapter
from msdnet.training.nn.denoiser import DenoiserStep, LightDenoiser, ddim_loop
from msdnet.training.nn.encoder import SparseEncoder, level_shapes
from msdnet.training.nn.grad_balance import GradBalance, loop_steps
from msdnet.training.nn.heads import build_head
from msdnet.training.nn.rgfd import RGFD
from msdnet.training.nn.s2d import S2D
from msdnet.training.nn.unet import R2LDMStep, R2LDMUNet

MODEL_KINDS = ("teacher", "student", "r2ldm")


def _full_scale(head: nn.Module, features: Tensor) -> tuple[Tensor, Tensor]:
    """F^D (B, C, H8, W8) -> (occupancy (B, D, H, W), offsets (B, 3, D, H, W))."""
    occ, off = head(features)
    return occ.squeeze(1), off


class TeacherModel(nn.Module):
    """LiDAR encoder -> S2D enhancement -> F_l^D -> reconstruction head."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = SparseEncoder(cfg, "lidar")
        self.s2d = S2D(cfg)
        self.head = build_head(cfg)

    def features(self, lidar: EncoderInput) -> Tensor:
        """F_l^D (B, C, H8, W8), the dense teacher features (distillation target)."""
        return self.s2d(self.encoder.encode(lidar))

    def losses(self, batch: Batch) -> dict[str, Tensor]:
        """Eq. 7 on the LiDAR targets: {"loss", "recon", "occ_s4", "off_s4", ..., "off_s1"}."""
        terms = head_loss(
            self.head, self.features(batch.lidar), batch.targets, self.cfg.losses, self.training
        )
        return {"loss": terms["recon"], **terms}

    def predict(self, inp: EncoderInput, noise: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """LiDAR input -> full-scale (occupancy, offsets); ``noise`` is unused."""
        return _full_scale(self.head, self.features(inp))


class _FrozenTeacherMixin(nn.Module):
    """Holds the frozen teacher; keeps it in eval mode whatever ``train()`` is called with."""

    teacher: TeacherModel

    def _attach_teacher(self, cfg: ModelConfig, teacher: TeacherModel | None) -> None:
        teacher = TeacherModel(cfg) if teacher is None else teacher
        if teacher.cfg.grid != cfg.grid or teacher.cfg.bev_channels != cfg.bev_channels:
            raise ValueError("the teacher's grid / bev_channels differ from this model's config")
        teacher.requires_grad_(False)
        self.teacher = teacher.eval()
        abar = torch.tensor(alphas_cumprod(cfg.diffusion), dtype=torch.float32)  # (T + 1,)
        self.register_buffer("abar", abar, persistent=False)
        shift, scale = norm_tensors(cfg)
        self.register_buffer("latent_shift", shift, persistent=False)  # (1, C, 1, 1)
        self.register_buffer("latent_scale", scale, persistent=False)  # (1, C, 1, 1)

    def train(self, mode: bool = True) -> _FrozenTeacherMixin:
        super().train(mode)
        self.teacher.eval()
        return self

    @property
    def head(self) -> LatentHead:
        """The teacher's reconstruction head (frozen) on normalised latents (training/models/latent.py)."""
        return LatentHead(self.teacher.head, self.latent_shift, self.latent_scale)

    def _teacher_latent(self, batch: Batch) -> tuple[Tensor, Tensor]:
        """(normalised F_l^D (B, C, H8, W8) without gradient, non-empty BEV cells (B, H8, W8) bool)."""
        with torch.no_grad():
            f_l = (self.teacher.features(batch.lidar) - self.latent_shift) / self.latent_scale
        return f_l, batch.lidar.bev_mask(tuple(f_l.shape[2:]))

    def _noised(self, x0: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Eq. 9 with t ~ U{1..T} per sample: (x_t, t (B,) float32, eps), all like x0."""
        t = torch.randint(1, self.cfg.diffusion.num_train_steps + 1, (x0.shape[0],), device=x0.device)
        a = self.abar[t].reshape(-1, 1, 1, 1)  # (B, 1, 1, 1)
        eps = torch.randn_like(x0)
        return a.sqrt() * x0 + (1.0 - a).sqrt() * eps, t.float(), eps


class StudentModel(_FrozenTeacherMixin):
    """MSDNet: radar encoder -> RGFD -> noise adapter -> DDIM loop -> shared head."""

    def __init__(self, cfg: ModelConfig, teacher: TeacherModel | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = SparseEncoder(cfg, "radar")
        self.rgfd = RGFD(cfg) if cfg.use_rgfd else nn.Identity()
        self.adapter = NoiseAdapter(cfg) if cfg.use_adapter else ForwardNoising(cfg)
        self.step = DenoiserStep(LightDenoiser(cfg))  # what denoiser_step.onnx computes
        w = cfg.losses
        # per-loss gradient normalisation of the denoiser (training only; a persistent buffer)
        self.grad_balance = (
            GradBalance(w.denoiser_grad_ratio)
            if w.denoiser_distill_grad and w.denoiser_grad_ratio > 0
            else None
        )
        self._attach_teacher(cfg, teacher)
        # --head-only: train only the head (the teacher copy this student holds) on F_r^D
        self.head_only = False
        # --distill: (frozen step, its (N, 3) coefficients), kept out of the state_dict
        self._distill_from: tuple[nn.Module, Tensor] | None = None
        self.distill_head = 0.0  # weight of the occupancy term (TrainConfig.distill_head)
        train_coeffs = step_coefficients(cfg.diffusion, sample_steps=cfg.train_sample_steps)
        self.register_buffer("train_coeffs", torch.tensor(train_coeffs), persistent=False)

    @property
    def denoiser(self) -> LightDenoiser:
        """The light eps-prediction network inside the DDIM step."""
        return self.step.denoiser

    def reconstructed(self, radar: EncoderInput) -> Tensor:
        """F_r^R (B, C, H8, W8): RGFD on the radar BEV features (F_r^S itself without RGFD)."""
        return self.rgfd(self.encoder.encode(radar))

    def denoised(self, f_r: Tensor, noise: Tensor, coeffs: np.ndarray | Tensor) -> Tensor:
        """F_r^D: adapter (Eq. 12) then the DDIM loop over ``coeffs`` rows [t, abar_t, abar_prev];
        F_r^R itself when the config has no DGFD."""
        if not self.cfg.use_dgfd:
            return f_r
        return ddim_loop(self._loop_steps(len(coeffs)), self.adapter(f_r, noise), coeffs)

    def _loop_steps(self, n_steps: int) -> nn.Module | list[Callable[..., Tensor]]:
        """The DDIM steps the training loop runs. Unless ``losses.denoiser_distill_grad``, they use
        detached copies of the denoiser's weights: gradients still flow through the loop's
        activations into the adapter and RGFD, but the denoiser learns from Eq. 10 alone. With it,
        ``denoiser_grad_steps`` / ``denoiser_grad_ratio`` truncate and normalise the loop's
        gradient on the denoiser (training/nn/grad_balance.py)."""
        w = self.cfg.losses
        if not self.training or self.head_only:  # head_only: the loop runs under no_grad
            return self.step
        if not w.denoiser_distill_grad:
            return loop_steps(self.step, n_steps, -1, None)  # every step detached
        if w.denoiser_grad_steps <= 0 and self.grad_balance is None:
            return self.step
        return loop_steps(self.step, n_steps, w.denoiser_grad_steps, self.grad_balance)

    def _eps_hat(self, x_t: Tensor, t: Tensor) -> Tensor:
        """The denoiser on Eq. 10's input, through the gradient tap when normalising."""
        if self.grad_balance is None or not self.training:
            return self.denoiser(x_t, t)
        ones = torch.ones((), dtype=torch.float32)
        return functional_call(self.denoiser, self.grad_balance.tapped(self.denoiser, 0, ones), (x_t, t))

    def losses(self, batch: Batch) -> dict[str, Tensor]:
        """Eq. 15: {"loss", "recon", "distill_rec", "distill_diff", "diff", per-scale occ/off,
        "align" (the adapter's alignment loss, when ``losses.adapter_align > 0``), "gate" (mean
        adapter gate delta; a diagnostic, not in the loss)}."""
        if self.head_only:
            return self._head_losses(batch)
        if self._distill_from is not None:
            return self._distill_losses(batch)
        w = self.cfg.losses
        if self.grad_balance is not None and self.training:
            self.grad_balance.fold()  # the previous step's gradient norms
        f_l, nonempty = self._teacher_latent(batch)
        f_r = self.reconstructed(batch.radar)
        zero = f_r.new_zeros(())
        out = {"distill_rec": zero, "distill_diff": zero, "diff": zero}
        eps_m = torch.randn_like(f_r)
        if self.cfg.use_dgfd and w.adapter_align > 0 and isinstance(self.adapter, NoiseAdapter):
            delta = self.adapter.gate(f_r)  # (B, C, 1, 1)
            # the loop sees the gate as a constant; F_r^R still trains through it
            f_d = ddim_loop(
                self._loop_steps(len(self.train_coeffs)),
                self.adapter.mix(f_r, eps_m, delta.detach()),
                self.train_coeffs,
            )
            a_m = self.abar[self.cfg.diffusion.start_step]
            target = a_m.sqrt() * f_l + (1.0 - a_m).sqrt() * eps_m  # Eq. 9 at m, same eps
            out["align"] = eps_loss(self.adapter.mix(f_r.detach(), eps_m, delta), target)
        else:
            f_d = self.denoised(f_r, eps_m, self.train_coeffs)
        recon = head_loss(self.head, f_d, batch.targets, w, self.training)
        out["distill_rec"] = feature_distillation(f_r, f_l, nonempty, w.alpha, w.gamma)  # Eq. 8
        if self.cfg.use_dgfd:
            out["distill_diff"] = feature_distillation(f_d, f_l, nonempty, w.alpha, w.gamma)  # Eq. 14
            x_t, t, eps = self._noised(f_l)
            out["diff"] = eps_loss(self._eps_hat(x_t, t), eps)  # Eq. 10
            if self.grad_balance is not None:  # diagnostics: the loop / Eq. 10 gradient norms
                d, loop = self.grad_balance.smoothed.tolist()
                out["grad_ratio"] = f_r.new_tensor((loop / d) ** 0.5 if d > 0 else 0.0)
                out["grad_scale"] = self.grad_balance.scale().to(f_r)
            if isinstance(self.adapter, NoiseAdapter):
                with torch.no_grad():
                    out["gate"] = self.adapter.gate(f_r).mean()
        total = student_total(recon["recon"], out["distill_rec"], out["distill_diff"], out["diff"], w)
        if "align" in out:
            total = total + w.adapter_align * out["align"]
        return {"loss": total, **out, **recon}

    def enable_distillation(self, source: nn.Module, steps: int, head_weight: float = 0.0) -> None:
        """Few-step distillation (``msdnet-train student --distill N --loop-steps K``): ``source``,
        the step module of the loop being distilled (frozen here), runs N DDIM steps from x_m; this
        student's own step must reach the same F_r^D in K (``train_coeffs``). Direct distillation of
        the deterministic (eta = 0) sampler: x_m -> x_0 is a fixed map, so each batch is its own
        target, no progressive halving needed. Only the denoiser should be left trainable."""
        frozen = source.requires_grad_(False).eval()
        coeffs = torch.tensor(step_coefficients(self.cfg.diffusion, sample_steps=steps))  # (N, 3)
        self._distill_from = (frozen, coeffs)
        self.distill_head = head_weight

    def _distill_losses(self, batch: Batch) -> dict[str, Tensor]:
        """{"loss", "distill": MSE of the K-step F_r^D to the N-step one, "distill_occ": the same for the
        full-scale occupancy the head decodes (with ``distill_head``), "span" (x_m against N steps);
        in eval mode (validation) also "undistilled" (the frozen loop at K steps against its own
        N steps; "undistilled_occ"), kept off the training steps: K more steps and a head call}."""
        assert self._distill_from is not None
        source, coeffs = self._distill_from
        with torch.no_grad():
            f_r = self.reconstructed(batch.radar)
            x_m = self.adapter(f_r, torch.randn_like(f_r))  # Eq. 12
            target = ddim_loop(source, x_m, coeffs)  # (B, C, H8, W8) the N-step loop
            before = None if self.training else ddim_loop(source, x_m, self.train_coeffs)
        x_k = ddim_loop(self.step, x_m, self.train_coeffs)
        mse = torch.nn.functional.mse_loss
        out = {"distill": mse(x_k, target), "span": mse(x_m, target)}
        if before is not None:
            out["undistilled"] = mse(before, target)
        if self.distill_head > 0:  # the frozen head on both: (B, D, H, W) occupancy in [0, 1]
            with torch.no_grad():
                occ_target = _full_scale(self.head, target)[0]
                if before is not None:
                    out["undistilled_occ"] = mse(_full_scale(self.head, before)[0], occ_target)
            out["distill_occ"] = mse(_full_scale(self.head, x_k)[0], occ_target)
        out["loss"] = out["distill"] + self.distill_head * out.get("distill_occ", 0.0)
        return out

    def _head_losses(self, batch: Batch) -> dict[str, Tensor]:
        """Eq. 7 on the student's own F_r^D (the training loop's T_m), the rest frozen: what
        ``--head-only`` trains on a student (its copy of the head; the teacher's encoder, so the
        distillation target, untouched): {"loss", "recon", per-scale occ/off}."""
        with torch.no_grad():
            f_r = self.reconstructed(batch.radar)
            f_d = self.denoised(f_r, torch.randn_like(f_r), self.train_coeffs)
        terms = head_loss(self.head, f_d, batch.targets, self.cfg.losses, self.training)
        return {"loss": terms["recon"], **terms}

    def predict(
        self, inp: EncoderInput, noise: Tensor | None = None, sample_steps: int | None = None
    ) -> tuple[Tensor, Tensor]:
        """Radar input, eps (B, C, H8, W8) (default: torch.randn) -> full-scale (occ, off),
        with ``sample_steps`` DDIM steps from m (default cfg.diffusion.sample_steps)."""
        f_r = self.reconstructed(inp)
        noise = torch.randn_like(f_r) if noise is None else noise
        coeffs = step_coefficients(self.cfg.diffusion, sample_steps=sample_steps)
        return _full_scale(self.head, self.denoised(f_r, noise, coeffs))


class R2LDMModel(_FrozenTeacherMixin):
    """R2LDM baseline: conditional latent diffusion from noise, decoded by the teacher's head.

    Beyond the paper (both off by default, docs/training.md): ``losses.r2ldm_cond_align`` adds a
    1x1 head regressing the teacher latent from the condition (training only), and
    ``r2ldm_cond_dropout`` trains without condition on that share of frames, for the classifier-
    free guidance ``r2ldm_guidance`` that the step (and ``r2ldm_step.onnx``) applies.
    """

    def __init__(self, cfg: ModelConfig, teacher: TeacherModel | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = SparseEncoder(cfg, "radar")
        # what r2ldm_step.onnx computes
        self.step = R2LDMStep(R2LDMUNet(cfg), cfg.r2ldm_x0_clip, cfg.r2ldm_guidance)
        if cfg.losses.r2ldm_cond_align > 0:  # training only, not exported
            self.cond_head = nn.Conv2d(cfg.bev_channels, cfg.bev_channels, 1)
        self._attach_teacher(cfg, teacher)

    @property
    def unet(self) -> R2LDMUNet:
        """The eps-prediction U-Net inside the DDIM step."""
        return self.step.unet

    def losses(self, batch: Batch) -> dict[str, Tensor]:
        """R2LDM stage 2: L2 eps-prediction on noised F_l^D given c = F_r^S: {"loss", "diff"}.

        Outside training (validation), also the conditioning check ``diff_shuffled``: the same
        x_t, t and eps with each frame given the previous frame's condition in the batch (a batch
        of one: its own condition mirrored left-right, so every frame counts in both means); a
        model that follows its radar input has ``diff`` well below it.
        """
        f_l, _ = self._teacher_latent(batch)
        cond = self.encoder.encode(batch.radar)
        x_t, t, eps = self._noised(f_l)
        c = cond
        if self.training and self.cfg.r2ldm_cond_dropout > 0:  # classifier-free guidance: no condition
            keep = torch.rand(cond.shape[0], device=cond.device) >= self.cfg.r2ldm_cond_dropout
            c = cond * keep.to(cond.dtype).reshape(-1, 1, 1, 1)
        diff = eps_loss(self.unet(x_t, t, c), eps)
        out = {"loss": diff, "diff": diff}
        if self.cfg.losses.r2ldm_cond_align > 0:
            out["cond_align"] = eps_loss(self.cond_head(cond), f_l)  # MSE to the teacher latent
            out["loss"] = diff + self.cfg.losses.r2ldm_cond_align * out["cond_align"]
        if not self.training:
            other = cond.roll(1, dims=0) if cond.shape[0] > 1 else cond.flip(-1)
            out["diff_shuffled"] = eps_loss(self.unet(x_t, t, other), eps)
        return out

    def predict(
        self, inp: EncoderInput, noise: Tensor | None = None, sample_steps: int | None = None
    ) -> tuple[Tensor, Tensor]:
        """Radar input, x_T (B, C, H8, W8) (default: torch.randn) -> full-scale (occ, off), with
        ``sample_steps`` DDIM steps from T (default cfg.r2ldm_sample_steps)."""
        cond = self.encoder.encode(inp)
        x = torch.randn_like(cond) if noise is None else noise
        steps = self.cfg.r2ldm_sample_steps if sample_steps is None else sample_steps
        coeffs = step_coefficients(
            self.cfg.diffusion, sample_steps=steps, start=self.cfg.diffusion.num_train_steps
        )
        return _full_scale(self.head, ddim_loop(self.step, x, coeffs, cond=cond))


def build_model(kind: str, cfg: ModelConfig, teacher: TeacherModel | None = None) -> nn.Module:
    """kind: "teacher" | "student" | "r2ldm". The student and R2LDM take the trained teacher and
    freeze it in place (``requires_grad_(False)``, eval mode); without one they get a fresh
    teacher whose weights a checkpoint must load (their checkpoints carry the teacher's)."""
    if cfg.r2ldm_recipe == "published" and kind in ("teacher", "r2ldm"):
        from msdnet.training.models.r2ldm_published import build_published  # R2LDM as published

        return build_published(kind, cfg, teacher)
    if kind == "teacher":
        return TeacherModel(cfg)
    if kind == "student":
        return StudentModel(cfg, teacher)
    if kind == "r2ldm":
        return R2LDMModel(cfg, teacher)
    raise ValueError(f"model kind must be one of {MODEL_KINDS}, got {kind!r}")


def bev_shape(cfg: ModelConfig) -> tuple[int, int, int]:
    """(C, H8, W8) of every BEV map (F^S, F^R, F^D, the noise eps) for this config; the published
    R2LDM's latent (L, H4, W4) for that recipe."""
    if cfg.r2ldm_recipe == "published":
        from msdnet.training.models.r2ldm_published import latent_shape

        return latent_shape(cfg)
    _, h8, w8 = level_shapes(cfg.grid)[-1]
    return cfg.bev_channels, h8, w8
