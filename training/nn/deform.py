"""Deformable 2D convolution (DCNv1) in pure torch, exported as the ONNX ``DeformConv`` op.

Semantics are those of ONNX ``DeformConv`` (opset 19) with ``group = offset_group = 1`` and no
mask, which are also torchvision's ``deform_conv2d``:

- output cell ``(oy, ox)`` and kernel tap ``(i, j)`` (taps row-major, ``k = i * kw + j``) sample
  the input at ``y = oy * stride_h - pad_h + i * dil_h + dy``,
  ``x = ox * stride_w - pad_w + j * dil_w + dx``;
- ``offset`` is ``(B, 2 * kh * kw, H_out, W_out)`` holding ``(dy, dx)`` pairs per tap:
  channel ``2 k`` is ``dy`` and ``2 k + 1`` is ``dx``;
- sampling is bilinear; each of the four corners outside the input contributes zero
  (zero padding), so a point at or beyond one pixel outside the map samples zero.

Training runs :func:`deform_conv2d` (gather-based bilinear sampling, differentiable in the input,
the weights and the offsets; no torchvision here). Under ``torch.onnx.export(..., dynamo=False)``
the module calls the opaque custom op ``msdnet::deform_conv2d`` instead (the tracer records one
node; an ``autograd.Function`` with ``symbolic`` traces its body into a sub-block that torch 2.13's
peephole pass rejects), and the registered symbolic emits one ``DeformConv`` node, which
onnxruntime 1.32's CPU provider runs (tests/test_deform.py: equal to the torch forward).
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor, nn
from torch.onnx import symbolic_helper

ONNX_OPSET = 19  # first opset with DeformConv


def _pair(v: int | tuple[int, int]) -> tuple[int, int]:
    return (v, v) if isinstance(v, int) else (int(v[0]), int(v[1]))


def deform_conv2d(
    x: Tensor,
    offset: Tensor,
    weight: Tensor,
    bias: Tensor | None = None,
    stride: tuple[int, int] = (1, 1),
    padding: tuple[int, int] = (1, 1),
    dilation: tuple[int, int] = (1, 1),
) -> Tensor:
    """Deformable convolution, ONNX ``DeformConv`` semantics (see the module docstring).

    x: (B, C, H, W) float; offset: (B, 2 * kh * kw, H_out, W_out) [(dy, dx) per tap];
    weight: (O, C, kh, kw); bias: (O,) or None -> (B, O, H_out, W_out).
    """
    b, c, h, w = x.shape
    o, _, kh, kw = weight.shape
    ho, wo = offset.shape[-2:]
    k = kh * kw
    dev, dt = x.device, x.dtype
    off = offset.reshape(b, k, 2, ho, wo)  # (B, K, [dy, dx], H_out, W_out)
    tap_y = (torch.arange(kh, device=dev, dtype=dt) * dilation[0]).repeat_interleave(kw)  # (K,)
    tap_x = (torch.arange(kw, device=dev, dtype=dt) * dilation[1]).repeat(kh)  # (K,)
    out_y = torch.arange(ho, device=dev, dtype=dt) * stride[0] - padding[0]  # (H_out,)
    out_x = torch.arange(wo, device=dev, dtype=dt) * stride[1] - padding[1]  # (W_out,)
    py = (tap_y[:, None, None] + out_y[None, :, None]) + off[:, :, 0]  # (B, K, H_out, W_out)
    px = (tap_x[:, None, None] + out_x[None, None, :]) + off[:, :, 1]  # (B, K, H_out, W_out)
    y0 = torch.floor(py)
    x0 = torch.floor(px)
    ly = py - y0  # fractional parts carry the gradient to the offsets
    lx = px - x0
    flat = x.reshape(b, c, h * w)  # (B, C, H*W)
    sampled = x.new_zeros(b, c, k * ho * wo)
    for cy, cx, wgt in (
        (0, 0, (1 - ly) * (1 - lx)),
        (0, 1, (1 - ly) * lx),
        (1, 0, ly * (1 - lx)),
        (1, 1, ly * lx),
    ):
        yc = y0 + cy
        xc = x0 + cx
        valid = (yc >= 0) & (yc <= h - 1) & (xc >= 0) & (xc <= w - 1)
        idx = (yc.clamp(0, h - 1) * w + xc.clamp(0, w - 1)).long()  # (B, K, H_out, W_out)
        vals = torch.gather(flat, 2, idx.reshape(b, 1, -1).expand(b, c, -1))  # (B, C, K*Ho*Wo)
        sampled = sampled + vals * (wgt * valid).reshape(b, 1, -1)
    cols = sampled.reshape(b, c * k, ho * wo)  # row c * K + k, matching weight.reshape(O, C*K)
    out = torch.matmul(weight.reshape(o, c * k), cols)  # (B, O, H_out * W_out)
    if bias is not None:
        out = out + bias[None, :, None]
    return out.reshape(b, o, ho, wo)


@torch.library.custom_op("msdnet::deform_conv2d", mutates_args=())
def _deform_conv2d_op(
    x: Tensor,
    weight: Tensor,
    offset: Tensor,
    bias: Tensor,
    stride: list[int],
    padding: list[int],
    dilation: list[int],
) -> Tensor:
    """Opaque op used only while exporting: the tracer records one node, exported as DeformConv."""
    return deform_conv2d(x, offset, weight, bias, _pair(stride), _pair(padding), _pair(dilation))


@_deform_conv2d_op.register_fake
def _(x, weight, offset, bias, stride, padding, dilation):  # type: ignore[no-untyped-def]
    return x.new_empty(x.shape[0], weight.shape[0], offset.shape[2], offset.shape[3])


@symbolic_helper.parse_args("v", "v", "v", "v", "is", "is", "is")
def _deform_conv2d_symbolic(g, x, weight, offset, bias, stride, padding, dilation):  # type: ignore[no-untyped-def]
    """ONNX DeformConv (opset 19): inputs X, W, offset, B; pads are [top, left, bottom, right]."""
    return g.op(
        "DeformConv",
        x,
        weight,
        offset,
        bias,
        kernel_shape_i=symbolic_helper._get_tensor_sizes(weight)[2:],
        strides_i=stride,
        pads_i=[padding[0], padding[1], padding[0], padding[1]],
        dilations_i=dilation,
        group_i=1,
        offset_group_i=1,
    )


with warnings.catch_warnings():  # the TorchScript exporter's registry is deprecated, still works
    warnings.simplefilter("ignore", DeprecationWarning)
    torch.onnx.register_custom_op_symbolic("msdnet::deform_conv2d", _deform_conv2d_symbolic, ONNX_OPSET)


class DeformConv2d(nn.Module):
    """Deformable conv whose offsets are predicted from its input by a zero-initialised conv.

    x: (B, in_ch, H, W) -> (B, out_ch, H_out, W_out) with H_out = (H + 2 p - d (k - 1) - 1) // s + 1.
    At initialisation the offsets are zero and the layer equals a plain ``conv2d``.
    """

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        kernel: int = 3,
        stride: int = 1,
        padding: int = 1,
        dilation: int = 1,
        bias: bool = True,
    ) -> None:
        super().__init__()
        self.stride = _pair(stride)
        self.padding = _pair(padding)
        self.dilation = _pair(dilation)
        self.weight = nn.Parameter(torch.empty(out_ch, in_ch, kernel, kernel))
        nn.init.kaiming_uniform_(self.weight, a=5**0.5)  # nn.Conv2d's default
        bound = 1.0 / (in_ch * kernel * kernel) ** 0.5
        self.bias = nn.Parameter(torch.empty(out_ch).uniform_(-bound, bound)) if bias else None
        self.offset_conv = nn.Conv2d(
            in_ch, 2 * kernel * kernel, kernel, stride, padding, dilation
        )  # (B, 2*k*k, H_out, W_out) [(dy, dx) per tap]
        nn.init.zeros_(self.offset_conv.weight)
        nn.init.zeros_(self.offset_conv.bias)

    def forward(self, x: Tensor) -> Tensor:
        """x: (B, in_ch, H, W) -> (B, out_ch, H_out, W_out)."""
        return self.forward_with_offset(x, self.offset_conv(x))

    def forward_with_offset(self, x: Tensor, offset: Tensor) -> Tensor:
        """x: (B, in_ch, H, W), offset: (B, 2*k*k, H_out, W_out) -> (B, out_ch, H_out, W_out)."""
        if torch.onnx.is_in_onnx_export():
            bias = self.bias if self.bias is not None else self.weight.new_zeros(self.weight.shape[0])
            return _deform_conv2d_op(
                x, self.weight, offset, bias, [*self.stride], [*self.padding], [*self.dilation]
            )
        return deform_conv2d(x, offset, self.weight, self.bias, self.stride, self.padding, self.dilation)
