"""The R2LDM baseline follows its condition: U-Net widths, condition normalisation, x0 clip,
the validation conditioning check, and the stage-2 learning rate."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from msdnet.runtime.spec import ddim
from msdnet.training.config import MODEL_PRESETS, R2LDM_LR
from msdnet.training.models.assembly import R2LDMModel
from msdnet.training.models.losses import eps_loss
from msdnet.training.nn.denoiser import ddim_update
from msdnet.training.nn.unet import R2LDMStep, R2LDMUNet, ddim_update_clipped

TINY = MODEL_PRESETS["tiny"]
RAW_COND_STD = 0.03  # the scale of an untrained radar encoder's F_r^S (the 2026-11 audit: 0.032)
COND_RATIO_GOAL = 0.9  # eps-MSE with the own condition <= this x with a shuffled one (issue 13)


def _abar(cfg=TINY) -> torch.Tensor:
    return torch.tensor(ddim.alphas_cumprod(cfg.diffusion), dtype=torch.float32)


def _synthetic(n: int, gen: torch.Generator, cfg=TINY) -> tuple[torch.Tensor, torch.Tensor]:
    """(x0 (n, C, H, W) unit variance, cond (n, C, H, W)): the condition determines x0 exactly, but
    at the raw encoder's small scale, so a U-Net that does not normalise it finds it hard to use."""
    c, h, w = cfg.bev_channels, 4, 4
    x0 = torch.randn(n, c, h, w, generator=gen)
    return x0, RAW_COND_STD * x0.flip(1)  # channel-permuted copy


def test_input_width_must_carry_the_noise():
    with pytest.raises(ValueError, match="r2ldm_channels"):
        R2LDMUNet(dataclasses.replace(TINY, r2ldm_channels=(16, 32)))  # 16 < 2C = 32
    for name in ("tiny", "lite", "paper"):
        cfg = MODEL_PRESETS[name]
        assert cfg.r2ldm_channels[0] >= 2 * cfg.bev_channels


def test_fresh_unet_is_the_linear_guess():
    """Zero-initialised output: eps_hat = sqrt(1 - abar_t) x_t, whatever the condition."""
    torch.manual_seed(0)
    unet = R2LDMUNet(TINY).eval()
    x, cond = torch.randn(2, 16, 4, 4), torch.randn(2, 16, 4, 4)
    t = torch.tensor([300.0, 700.0])
    with torch.no_grad():
        got = unet(x, t, cond)
    want = (1.0 - _abar()[t.long()]).sqrt().reshape(-1, 1, 1, 1) * x
    torch.testing.assert_close(got, want)


def test_x0_clip_bounds_the_sample_and_is_exact_when_inactive():
    torch.manual_seed(0)
    x_t, eps = torch.randn(1, 16, 4, 4), 50.0 * torch.randn(1, 16, 4, 4)
    a_t, a_prev = torch.tensor([0.01]), torch.tensor([1.0])  # last step: x_prev = x0
    clipped = ddim_update_clipped(x_t, eps, a_t, a_prev, clip=3.0)
    assert clipped.abs().max() <= 3.0 + 1e-5
    assert ddim_update(x_t, eps, a_t, a_prev).abs().max() > 100.0  # unclipped, the estimate explodes
    small = 0.1 * torch.randn(1, 16, 4, 4)
    a_prev = torch.tensor([0.02])
    torch.testing.assert_close(
        ddim_update_clipped(x_t, small, a_t, a_prev, clip=1e3), ddim_update(x_t, small, a_t, a_prev)
    )
    torch.testing.assert_close(
        ddim_update_clipped(x_t, eps, a_t, a_prev, clip=0.0), ddim_update(x_t, eps, a_t, a_prev)
    )


def test_step_applies_the_config_clip():
    cfg = dataclasses.replace(TINY, r2ldm_x0_clip=2.0)
    model = R2LDMModel(cfg)
    assert isinstance(model.step, R2LDMStep) and model.step.x0_clip == 2.0
    x_t = 40.0 * torch.randn(1, 16, 4, 4)  # far outside any latent
    with torch.no_grad():
        out = model.step(x_t, torch.randn(1, 16, 4, 4), torch.tensor([999.0]), torch.tensor([4e-5]),
                         torch.tensor([1.0]))  # fmt: skip
    assert out.abs().max() <= 2.0 + 1e-5


def test_unet_learns_to_follow_a_small_scale_condition():
    """A tiny U-Net trained for 80 steps on latents that the (0.03-scale) condition fixes
    must score eps-MSE with its own condition <= 0.9 x with a shuffled one (the 2026-11 U-Net,
    without the condition normalisation, scored the same with either)."""
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(1)
    unet = R2LDMUNet(TINY)
    opt = torch.optim.Adam(unet.parameters(), lr=2e-3)
    abar = _abar()
    for _ in range(80):  # ~5 s; own / shuffled ~0.79 here, 0.5 after 150 steps
        x0, cond = _synthetic(16, gen)
        t = torch.randint(1, TINY.diffusion.num_train_steps + 1, (16,), generator=gen)
        a = abar[t].reshape(-1, 1, 1, 1)
        eps = torch.randn(x0.shape, generator=gen)
        loss = eps_loss(unet((a.sqrt() * x0 + (1 - a).sqrt() * eps), t.float(), cond), eps)
        opt.zero_grad()
        loss.backward()
        opt.step()
    unet.eval()
    x0, cond = _synthetic(64, gen)
    own, shuffled = [], []
    with torch.no_grad():
        for t_val in np.linspace(50, 950, 10):
            t = torch.full((64,), float(int(t_val)))
            a = abar[t.long()].reshape(-1, 1, 1, 1)
            eps = torch.randn(x0.shape, generator=gen)
            x_t = a.sqrt() * x0 + (1 - a).sqrt() * eps
            own.append(float(eps_loss(unet(x_t, t, cond), eps)))
            shuffled.append(float(eps_loss(unet(x_t, t, cond.roll(1, dims=0)), eps)))
    assert np.mean(own) <= COND_RATIO_GOAL * np.mean(shuffled), (own, shuffled)


def test_validation_losses_carry_the_conditioning_check():
    from msdnet.training.data.batch import collate

    torch.manual_seed(0)
    model = R2LDMModel(TINY)
    rng = np.random.default_rng(0)
    frames = [
        (rng.uniform(0, 6, (30, 5)).astype(np.float32), rng.uniform(0, 6, (200, 3)).astype(np.float32))
        for _ in range(2)
    ]
    batch = collate(frames, TINY)
    model.train()
    assert set(model.losses(batch)) == {"loss", "diff"}
    model.eval()
    with torch.no_grad():
        out = model.losses(batch)
    assert {"loss", "diff", "diff_shuffled"} <= set(out)
    assert float(out["diff_shuffled"]) > 0.0
    with torch.no_grad():  # a batch of one still gets the check (its own condition mirrored)
        assert "diff_shuffled" in model.losses(collate(frames[:1], TINY))


def test_r2ldm_trains_at_the_stage_2_learning_rate(tmp_path):
    from msdnet.training.cli import _plan
    from msdnet.training.config import TRAIN_PRESETS

    n, tcfg = _plan("r2ldm", tmp_path / "run", False, None, TRAIN_PRESETS["lite"], {})
    assert tcfg.lr == R2LDM_LR and 1e-4 <= R2LDM_LR <= 2e-4
    assert _plan("r2ldm", tmp_path / "run", False, None, TRAIN_PRESETS["lite"], {"lr": 5e-4})[1].lr == 5e-4
    assert _plan("student", tmp_path / "run", False, None, TRAIN_PRESETS["lite"], {})[1].lr == 1e-3


def test_condition_alignment_is_an_r2ldm_training_term():
    from msdnet.training.data.batch import collate

    cfg = dataclasses.replace(TINY, losses=dataclasses.replace(TINY.losses, r2ldm_cond_align=0.5))
    torch.manual_seed(0)
    model = R2LDMModel(cfg)
    assert not hasattr(R2LDMModel(TINY), "cond_head")  # 0 = R2LDM as published
    rng = np.random.default_rng(0)
    frames = [(rng.uniform(0, 6, (30, 5)).astype(np.float32), rng.uniform(0, 6, (200, 3)).astype(np.float32))]
    out = model.losses(collate(frames, cfg))
    torch.testing.assert_close(out["loss"], out["diff"] + 0.5 * out["cond_align"])
    out["loss"].backward()  # the regression reaches the radar encoder
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.encoder.parameters())
    assert all(p.requires_grad is False for p in model.teacher.parameters())


def test_guided_step_mixes_conditional_and_unconditional_eps_and_exports():
    from test_dense_nets import ONNX_REL_ERR, onnx_session, rel_err, run_onnx

    from msdnet.runtime.model import onnx_spec

    cfg = dataclasses.replace(TINY, r2ldm_guidance=2.5)
    torch.manual_seed(0)
    model = R2LDMModel(cfg).eval()
    torch.nn.init.normal_(model.unet.out[2].weight, std=0.1)
    x, cond = torch.randn(2, 16, 4, 4), torch.randn(2, 16, 4, 4)
    t, a_t, a_prev = torch.tensor([500.0]), torch.tensor([0.08]), torch.tensor([0.1])
    with torch.no_grad():
        got = model.step(x, cond, t, a_t, a_prev)
        e_c, e_0 = model.unet(x, t, cond), model.unet(x, t, torch.zeros_like(cond))
        want = ddim_update_clipped(x, e_0 + 2.5 * (e_c - e_0), a_t, a_prev, cfg.r2ldm_x0_clip)
        unguided = R2LDMStep(model.unet, cfg.r2ldm_x0_clip)(x, cond, t, a_t, a_prev)
    torch.testing.assert_close(got, want)
    assert not torch.allclose(got, unguided, atol=1e-4)
    feeds = (x[:1], cond[:1], t, a_t, a_prev)
    spec = onnx_spec.R2LDM_STEP
    with torch.no_grad():
        ref = model.step(*feeds).numpy()
    assert rel_err(run_onnx(onnx_session(model.step, feeds, spec), spec, feeds), ref) <= ONNX_REL_ERR
