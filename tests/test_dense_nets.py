"""Dense BEV networks: blocks, RGFD, noise adapter, light denoiser + DDIM step, R2LDM U-Net."""

from __future__ import annotations

import io
import math
import warnings

import numpy as np
import onnxruntime as ort
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from msdnet.runtime.model import onnx_spec
from msdnet.runtime.spec import ddim
from msdnet.training.config import MODEL_PRESETS, ModelConfig
from msdnet.training.nn import (
    RGFD,
    DenoiserStep,
    LightDenoiser,
    NoiseAdapter,
    R2LDMStep,
    R2LDMUNet,
    ddim_loop,
    dense_parameter_counts,
)
from msdnet.training.nn.adapter import initial_gate
from msdnet.training.nn.blocks import (
    CBAM,
    Bottleneck2d,
    ChannelLayerNorm,
    ConvNeXtBlock,
    timestep_embedding,
)

ONNX_REL_ERR = 1e-4  # max |ort - torch| / max |torch| for every exported graph
REF_REL_ERR = 1e-5  # torch DDIM step vs the float64 numpy reference
PAPER_MSDNET_BUDGET = 20.5e6  # MSDNet paper, Tab. IV (whole model)
PAPER_R2LDM_TOTAL = 40.3e6  # R2LDM, as reported in MSDNet Tab. IV (whole model)


def bev(cfg: ModelConfig, batch: int = 2, seed: int = 0) -> torch.Tensor:
    """(B, C, H/8, W/8) random BEV map for a preset."""
    _, h, w = cfg.grid.shape_zyx
    g = torch.Generator().manual_seed(seed)
    return torch.randn(batch, cfg.bev_channels, h // 8, w // 8, generator=g)


def ddim_update_reference(x_t, eps, abar_t, abar_prev):
    """Numpy float64 reference of one deterministic DDIM step (runtime/spec/ddim.py step 5)."""
    x_t, eps = x_t.astype(np.float64), eps.astype(np.float64)
    x0 = (x_t - np.sqrt(1.0 - abar_t) * eps) / np.sqrt(abar_t)
    return np.sqrt(abar_prev) * x0 + np.sqrt(1.0 - abar_prev) * eps


def onnx_session(module: nn.Module, args: tuple, spec: onnx_spec.GraphSpec) -> ort.InferenceSession:
    """Export ``module`` traced on ``args`` (opset 19, TorchScript exporter) into an ORT session."""
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module.eval(),
            args,
            buf,
            opset_version=onnx_spec.OPSET,
            dynamo=False,
            input_names=list(spec.inputs),
            output_names=list(spec.outputs),
        )
    return ort.InferenceSession(buf.getvalue(), providers=["CPUExecutionProvider"])


def run_onnx(sess: ort.InferenceSession, spec: onnx_spec.GraphSpec, feeds: tuple) -> np.ndarray:
    """First output of ``sess`` on ``feeds`` given in ``spec.inputs`` order."""
    return sess.run(None, {n: a.numpy() for n, a in zip(spec.inputs, feeds, strict=True)})[0]


def rel_err(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.abs(got - want).max() / np.abs(want).max())


def coeff_row(cfg: ModelConfig, k: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Row k of step_coefficients as three (1,) float32 tensors [t], [abar_t], [abar_prev]."""
    row = torch.from_numpy(ddim.step_coefficients(cfg.diffusion)[k])
    return row[0:1], row[1:2], row[2:3]


# --- blocks -----------------------------------------------------------------------------------


def test_channel_layer_norm_equals_layer_norm():
    torch.manual_seed(0)
    ln = ChannelLayerNorm(6)
    with torch.no_grad():
        ln.weight.normal_()
        ln.bias.normal_()
    x = torch.randn(2, 6, 3, 5) * 3 + 1
    want = F.layer_norm(x.permute(0, 2, 3, 1), (6,), ln.weight, ln.bias, ln.eps).permute(0, 3, 1, 2)
    torch.testing.assert_close(ln(x), want, rtol=1e-5, atol=1e-5)


def test_blocks_keep_shape_and_behave():
    torch.manual_seed(0)
    x = torch.randn(2, 16, 5, 7)
    for block in (CBAM(16), ConvNeXtBlock(16), Bottleneck2d(16, 8)):
        assert block(x).shape == x.shape
    # CBAM only rescales: gates in (0, 1), so |y| <= |x| cell by cell.
    assert torch.all(CBAM(16)(x).abs() <= x.abs() + 1e-6)
    # ConvNeXt's layer scale starts at 1e-6: the block starts as the identity.
    assert (ConvNeXtBlock(16)(x) - x).abs().max() < 1e-3


def test_timestep_embedding_values():
    t = torch.tensor([0.0, 500.0])
    emb = timestep_embedding(t, 16)
    assert emb.shape == (2, 16)
    torch.testing.assert_close(emb[0], torch.cat([torch.ones(8), torch.zeros(8)]))
    assert emb[1, 0].item() == pytest.approx(math.cos(500.0), abs=1e-4)
    assert emb[1, 8].item() == pytest.approx(math.sin(500.0), abs=1e-4)
    f1 = math.exp(-math.log(10000.0) / 8)  # second frequency
    assert emb[1, 9].item() == pytest.approx(math.sin(500.0 * f1), abs=1e-4)
    odd = timestep_embedding(t, 7)
    assert odd.shape == (2, 7) and torch.all(odd[:, -1] == 0)


# --- RGFD and noise adapter -----------------------------------------------------------------


@pytest.mark.parametrize("preset", ["tiny", "lite"])
def test_rgfd_keeps_bev_shape(preset):
    cfg = MODEL_PRESETS[preset]
    x = bev(cfg)
    assert RGFD(cfg)(x).shape == x.shape


@pytest.mark.parametrize("size", [(5, 7), (3, 3), (1, 2)])
def test_rgfd_odd_sizes(size):
    cfg = MODEL_PRESETS["tiny"]
    x = torch.randn(1, cfg.bev_channels, *size)
    assert RGFD(cfg)(x).shape == x.shape


def test_rgfd_trains_deformable_offsets():
    cfg = MODEL_PRESETS["tiny"]
    model = RGFD(cfg)
    model(bev(cfg)).square().mean().backward()
    for down in (model.down1, model.down2):
        assert down.deform.offset_conv.weight.grad.abs().sum() > 0


def test_noise_adapter_mixes_features_and_noise():
    cfg = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    adapter = NoiseAdapter(cfg)
    f, eps = bev(cfg, seed=1) * 3, bev(cfg, seed=2)
    delta = adapter.gate(f)
    assert delta.shape == (2, cfg.bev_channels, 1, 1)
    assert torch.all((delta > 0) & (delta < 1))
    assert not torch.allclose(delta[0], delta[1])  # per-sample gate
    torch.testing.assert_close(adapter(f, eps), delta * f + (1 - delta) * eps)
    torch.testing.assert_close(adapter(f, f), f)  # noise equal to the features: nothing changes
    adapter(f, eps).square().mean().backward()
    assert adapter.bottleneck.body[0].weight.grad.abs().sum() > 0


def test_noise_adapter_starts_at_forward_chain_ratio():
    cfg = MODEL_PRESETS["paper"]
    abar_m = ddim.alphas_cumprod(cfg.diffusion)[cfg.diffusion.start_step]
    d0 = initial_gate(cfg)
    assert d0 / (1 - d0) == pytest.approx(math.sqrt(abar_m / (1 - abar_m)))
    adapter = NoiseAdapter(MODEL_PRESETS["tiny"])
    with torch.no_grad():
        adapter.mlp[2].weight.zero_()  # bias only: the gate is the initial ratio everywhere
    delta = adapter.gate(bev(MODEL_PRESETS["tiny"]))
    torch.testing.assert_close(delta, torch.full_like(delta, initial_gate(MODEL_PRESETS["tiny"])))


class _RGFDAdapter(nn.Module):
    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.rgfd, self.adapter = RGFD(cfg), NoiseAdapter(cfg)

    def forward(self, f_s: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
        return self.adapter(self.rgfd(f_s), eps)


def test_rgfd_adapter_onnx_matches_torch():
    """lite: 20 -> 10 -> 5 -> 10 -> 20, deformable offsets made non-zero."""
    cfg = MODEL_PRESETS["lite"]
    torch.manual_seed(0)
    model = _RGFDAdapter(cfg).eval()
    with torch.no_grad():
        for down in (model.rgfd.down1, model.rgfd.down2):
            down.deform.offset_conv.weight.normal_(0.0, 0.05)
            down.deform.offset_conv.bias.normal_(0.0, 1.0)
        model.rgfd.attention[1].gamma.fill_(0.5)  # make the ConvNeXt branch count
    f_s, eps = bev(cfg, 1, seed=3), bev(cfg, 1, seed=4)
    spec = onnx_spec.RGFD_ADAPTER
    got = run_onnx(onnx_session(model, (f_s, eps), spec), spec, (f_s, eps))
    with torch.no_grad():
        want = model(f_s, eps).numpy()
    assert rel_err(got, want) <= ONNX_REL_ERR


# --- light denoiser and DDIM ------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["msdnet", "r2ldm"])
@pytest.mark.parametrize("k", [0, 3, -1])  # first, middle, last step (abar_prev = 1)
def test_step_matches_numpy_reference(kind, k):
    cfg = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    x_t, cond = bev(cfg, seed=5), bev(cfg, seed=6)
    t, a_t, a_prev = coeff_row(cfg, k)
    with torch.no_grad():
        if kind == "msdnet":
            net = LightDenoiser(cfg)
            eps, got = net(x_t, t), DenoiserStep(net)(x_t, t, a_t, a_prev)
        else:
            unet = R2LDMUNet(cfg)
            eps, got = unet(x_t, t, cond), R2LDMStep(unet)(x_t, cond, t, a_t, a_prev)
    want = ddim_update_reference(x_t.numpy(), eps.numpy(), a_t.item(), a_prev.item())
    assert rel_err(got.numpy(), want) <= REF_REL_ERR


def test_per_sample_steps_in_a_batch():
    """Training feeds t and abar per sample, (B,): each sample must see only its own step."""
    cfg = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    step = DenoiserStep(_trained_head(LightDenoiser(cfg))).eval()
    x = bev(cfg, 2, seed=12)
    rows = torch.from_numpy(ddim.step_coefficients(cfg.diffusion)[[0, 20]])  # (2, 3)
    with torch.no_grad():
        both = step(x, rows[:, 0], rows[:, 1], rows[:, 2])
        for i in range(2):
            alone = step(x[i : i + 1], rows[i, 0:1], rows[i, 1:2], rows[i, 2:3])
            torch.testing.assert_close(both[i : i + 1], alone, rtol=1e-5, atol=1e-5)


class _OracleDenoiser(nn.Module):
    """Predicts the true noise: the DDIM loop must then return the clean features exactly."""

    def __init__(self, eps: torch.Tensor) -> None:
        super().__init__()
        self.eps = eps

    def forward(self, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return self.eps


def test_ddim_loop_with_oracle_noise_recovers_x0():
    cfg = MODEL_PRESETS["paper"]
    x0, eps = bev(MODEL_PRESETS["tiny"], seed=7), bev(MODEL_PRESETS["tiny"], seed=8)
    m = cfg.diffusion.start_step
    x_m = torch.from_numpy(ddim.q_sample(x0.numpy(), m, eps.numpy(), cfg.diffusion))
    out = ddim_loop(DenoiserStep(_OracleDenoiser(eps)), x_m, ddim.step_coefficients(cfg.diffusion))
    torch.testing.assert_close(out, x0, rtol=0, atol=1e-4)


def _trained_head(net: LightDenoiser) -> LightDenoiser:
    """The denoiser's head starts at zero (eps = its linear guess); give it weights, as training would."""
    with torch.no_grad():
        torch.nn.init.normal_(net.head[2].weight, std=0.1)
    return net


def test_ddim_loop_gradients_flow():
    cfg = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    net = LightDenoiser(cfg)
    x = bev(cfg).requires_grad_(True)
    t = torch.tensor([300.0])
    with torch.no_grad():  # the zero-initialised head starts at the linear guess sqrt(1 - abar_t) x_t
        a = float(ddim.alphas_cumprod(cfg.diffusion)[300])
        torch.testing.assert_close(net(x, t), (1.0 - a) ** 0.5 * x)
        torch.nn.init.normal_(net.head[2].weight, std=0.1)  # a trained head, for the gradients below
    coeffs = ddim.step_coefficients(cfg.diffusion, cfg.train_sample_steps)
    out = ddim_loop(DenoiserStep(net), x, coeffs)
    manual = x
    for t, a, ap in torch.from_numpy(coeffs):
        manual = DenoiserStep(net)(manual, t[None], a[None], ap[None])
    torch.testing.assert_close(out, manual)
    out.square().mean().backward()
    assert x.grad.abs().sum() > 0
    assert net.blocks[0].body[0].weight.grad.abs().sum() > 0
    assert net.time_proj.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("preset", ["tiny", "lite"])
def test_denoiser_step_onnx_matches_torch(preset):
    cfg = MODEL_PRESETS[preset]
    torch.manual_seed(0)
    step = DenoiserStep(_trained_head(LightDenoiser(cfg))).eval()
    x_t = bev(cfg, 1, seed=9)
    traced = (x_t, *coeff_row(cfg, 0))
    spec = onnx_spec.DENOISER_STEP
    sess = onnx_session(step, traced, spec)
    for k in (0, 7, -1):  # traced on row 0; other rows prove t and abar are real inputs
        feeds = (x_t, *coeff_row(cfg, k))
        with torch.no_grad():
            want = step(*feeds).numpy()
            assert k == 0 or not np.allclose(want, step(*traced).numpy(), atol=1e-5)
        assert rel_err(run_onnx(sess, spec, feeds), want) <= ONNX_REL_ERR


# --- R2LDM U-Net ------------------------------------------------------------------------------


@pytest.mark.parametrize(("preset", "size"), [("tiny", None), ("tiny", (5, 7)), ("lite", None)])
def test_unet_shapes(preset, size):
    cfg = MODEL_PRESETS[preset]
    x = bev(cfg, 1) if size is None else torch.randn(1, cfg.bev_channels, *size)
    with torch.no_grad():
        assert R2LDMUNet(cfg)(x, torch.tensor([999.0]), x).shape == x.shape


def test_unet_uses_condition_and_time():
    cfg = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    unet = R2LDMUNet(cfg).eval()
    torch.nn.init.normal_(unet.out[2].weight, std=0.1)  # zero-initialised: eps_hat = sqrt(1 - abar) x_t
    x, c1, c2 = bev(cfg, 1, 1), bev(cfg, 1, 2), bev(cfg, 1, 3)
    t1, t2 = torch.tensor([10.0]), torch.tensor([900.0])
    with torch.no_grad():
        base = unet(x, t1, c1)
        assert not torch.allclose(base, unet(x, t1, c2), atol=1e-4)
        assert not torch.allclose(base, unet(x, t2, c1), atol=1e-4)


def test_r2ldm_step_onnx_matches_torch():
    cfg = MODEL_PRESETS["tiny"]
    torch.manual_seed(0)
    step = R2LDMStep(R2LDMUNet(cfg)).eval()
    x_t, cond = bev(cfg, 1, seed=10), bev(cfg, 1, seed=11)
    t, a_t, a_prev = coeff_row(cfg, 2)
    feeds = (x_t, cond, t, a_t, a_prev)
    got = run_onnx(onnx_session(step, feeds, onnx_spec.R2LDM_STEP), onnx_spec.R2LDM_STEP, feeds)
    with torch.no_grad():
        want = step(x_t, cond, t, a_t, a_prev).numpy()
    assert rel_err(got, want) <= ONNX_REL_ERR


# --- sizes ------------------------------------------------------------------------------------


def test_parameter_counts_per_preset():
    counts = {name: dense_parameter_counts(cfg) for name, cfg in MODEL_PRESETS.items()}
    for name, per_module in counts.items():
        print(name, per_module)
    paper = counts["paper"]
    msdnet_dense = paper["rgfd"] + paper["noise_adapter"] + paper["light_denoiser"]
    assert msdnet_dense <= 0.2 * PAPER_MSDNET_BUDGET  # a few M of the 20.5 M budget
    assert paper["light_denoiser"] < 0.02 * paper["r2ldm_unet"]  # the point of the paper
    assert 0.75 * PAPER_R2LDM_TOTAL <= paper["r2ldm_unet"] <= PAPER_R2LDM_TOTAL
    for name in ("tiny", "lite"):
        assert sum(counts[name].values()) < sum(paper.values())
