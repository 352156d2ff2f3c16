"""DeformConv2d: ONNX DeformConv semantics in torch, onnxruntime agreement, gradients."""

from __future__ import annotations

import io
import warnings

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from msdnet.training.nn.deform import ONNX_OPSET, DeformConv2d, deform_conv2d

ORT_MAX_ABS_ERR = 1e-4  # torch forward vs onnxruntime on the exported DeformConv graph
REF_MAX_ABS_ERR = 1e-5  # torch (float32) vs the float64 loop reference below


def deform_conv_reference(x, offset, weight, bias, stride, pad, dil):
    """Loop reference of ONNX DeformConv (group 1, no mask), float64 numpy.

    x: (B, C, H, W); offset: (B, 2 kh kw, Ho, Wo) [(dy, dx) per row-major tap]; weight (O, C, kh, kw).
    """
    b, c, h, w = x.shape
    o, _, kh, kw = weight.shape
    ho, wo = offset.shape[2:]
    out = np.zeros((b, o, ho, wo)) + bias[None, :, None, None]

    def pixel(n, y, xx):  # (C,) zero outside the map
        if 0 <= y < h and 0 <= xx < w:
            return x[n, :, y, xx].astype(np.float64)
        return np.zeros(c)

    for n in range(b):
        for oy in range(ho):
            for ox in range(wo):
                for i in range(kh):
                    for j in range(kw):
                        k = i * kw + j
                        py = oy * stride - pad + i * dil + offset[n, 2 * k, oy, ox]
                        px = ox * stride - pad + j * dil + offset[n, 2 * k + 1, oy, ox]
                        y0, x0 = int(np.floor(py)), int(np.floor(px))
                        ly, lx = py - y0, px - x0
                        val = (
                            (1 - ly) * (1 - lx) * pixel(n, y0, x0)
                            + (1 - ly) * lx * pixel(n, y0, x0 + 1)
                            + ly * (1 - lx) * pixel(n, y0 + 1, x0)
                            + ly * lx * pixel(n, y0 + 1, x0 + 1)
                        )
                        out[n, :, oy, ox] += weight[:, :, i, j] @ val
    return out


class _WithOffset(nn.Module):
    """Exports the layer with the offsets as a graph input."""

    def __init__(self, layer: DeformConv2d) -> None:
        super().__init__()
        self.layer = layer

    def forward(self, x: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
        return self.layer.forward_with_offset(x, offset)


def _export(module: nn.Module, args: tuple, names: list[str]) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript exporter warns that it is deprecated
        warnings.simplefilter("ignore")
        torch.onnx.export(module, args, buf, opset_version=ONNX_OPSET, dynamo=False, input_names=names)
    return buf.getvalue()


def _out_size(n: int, stride: int, pad: int, dil: int, k: int = 3) -> int:
    return (n + 2 * pad - dil * (k - 1) - 1) // stride + 1


@pytest.mark.parametrize("stride", [1, 2])
def test_zero_offsets_equal_conv2d(stride):
    torch.manual_seed(0)
    layer = DeformConv2d(4, 6, 3, stride, 1)
    x = torch.randn(2, 4, 7, 9)
    want = F.conv2d(x, layer.weight, layer.bias, stride, 1)
    torch.testing.assert_close(layer(x), want, rtol=0, atol=1e-5)


@pytest.mark.parametrize(("stride", "pad", "dil"), [(1, 1, 1), (2, 1, 1), (1, 2, 2)])
def test_random_offsets_match_loop_reference(stride, pad, dil):
    rng = np.random.default_rng(stride + 10 * dil)
    x = rng.standard_normal((2, 3, 5, 6)).astype(np.float32)
    ho, wo = _out_size(5, stride, pad, dil), _out_size(6, stride, pad, dil)
    offset = (rng.standard_normal((2, 18, ho, wo)) * 2.5).astype(np.float32)  # many points outside
    weight = rng.standard_normal((4, 3, 3, 3)).astype(np.float32)
    bias = rng.standard_normal(4).astype(np.float32)
    got = deform_conv2d(
        *map(torch.from_numpy, (x, offset, weight, bias)), (stride, stride), (pad, pad), (dil, dil)
    )
    want = deform_conv_reference(x, offset, weight, bias, stride, pad, dil)
    assert np.abs(got.numpy() - want).max() <= REF_MAX_ABS_ERR * max(1.0, np.abs(want).max())


@pytest.mark.parametrize("stride", [1, 2])
def test_onnxruntime_matches_torch_random_offsets(stride):
    torch.manual_seed(stride)
    layer = DeformConv2d(5, 7, 3, stride, 1).eval()
    x = torch.randn(2, 5, 9, 11)
    ho, wo = _out_size(9, stride, 1, 1), _out_size(11, stride, 1, 1)
    offset = torch.randn(2, 18, ho, wo) * 3.0  # non-zero, some taps fall off the map
    model = _export(_WithOffset(layer), (x, offset), ["x", "offset"])
    assert [n.op_type for n in onnx.load_from_string(model).graph.node] == ["DeformConv"]
    sess = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    got = sess.run(None, {"x": x.numpy(), "offset": offset.numpy()})[0]
    with torch.no_grad():
        want = layer.forward_with_offset(x, offset).numpy()
    assert got.shape == want.shape == (2, 7, ho, wo)
    assert np.abs(got - want).max() <= ORT_MAX_ABS_ERR


def test_onnxruntime_matches_torch_predicted_offsets():
    """The whole layer (offset conv inside the graph) with a non-zero offset predictor."""
    torch.manual_seed(3)
    layer = DeformConv2d(6, 4, 3, 2, 1, bias=False).eval()
    with torch.no_grad():
        layer.offset_conv.weight.normal_(0.0, 0.5)
        layer.offset_conv.bias.normal_(0.0, 1.0)
    x = torch.randn(1, 6, 10, 10)
    with torch.no_grad():
        assert layer.offset_conv(x).abs().mean() > 0.5  # offsets are really non-zero
        want = layer(x).numpy()
    sess = ort.InferenceSession(_export(layer, (x,), ["x"]), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"x": x.numpy()})[0]
    assert np.abs(got - want).max() <= ORT_MAX_ABS_ERR


def test_offsets_get_gradients():
    torch.manual_seed(0)
    x = torch.randn(1, 2, 5, 5, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(3, 2, 3, 3, dtype=torch.float64, requires_grad=True)
    offset = (torch.rand(1, 18, 5, 5, dtype=torch.float64) * 1.6 - 0.8).requires_grad_(True)
    fn = lambda a, o, wt: deform_conv2d(a, o, wt, None)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (x, offset, weight), eps=1e-6, atol=1e-5)
    deform_conv2d(x, offset, weight).square().sum().backward()
    assert offset.grad is not None and offset.grad.abs().sum() > 0


def test_offset_predictor_trains_from_zero_init():
    torch.manual_seed(0)
    layer = DeformConv2d(3, 4)
    layer(torch.randn(2, 3, 6, 6)).square().mean().backward()
    assert layer.offset_conv.weight.grad.abs().sum() > 0  # zero-initialised but not dead
    assert layer.weight.grad.abs().sum() > 0
