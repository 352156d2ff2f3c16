"""The reconstruction head's 2x upsampling equals a 2x2x2 stride-2 transposed convolution."""

from __future__ import annotations

import torch

from msdnet.training.config import MODEL_PRESETS
from msdnet.training.data.targets import scale_shapes
from msdnet.training.nn.head import ReconHead, Up2x

TOL = 1e-5  # float32 reassociation between the two formulations


def test_up2x_equals_conv_transpose():
    torch.manual_seed(0)
    cin, cout = 3, 2
    up = Up2x(cin, cout)
    ref = torch.nn.ConvTranspose3d(cin, cout, 2, stride=2)
    # ConvTranspose weight (cin, cout, kz, ky, kx); Up2x's 1x1 conv output channel = child * cout + c
    w = up.proj.weight.detach().reshape(2, 2, 2, cout, cin)  # (dz, dy, dx, c_out, c_in)
    with torch.no_grad():
        ref.weight.copy_(w.permute(4, 3, 0, 1, 2))
        ref.bias.copy_(up.proj.bias.detach().reshape(8, cout)[0])
        up.proj.bias.copy_(ref.bias.repeat(8))
    x = torch.randn(2, cin, 3, 4, 5)
    torch.testing.assert_close(up(x), ref(x), atol=TOL, rtol=TOL)


def test_head_scales_match_targets():
    cfg = MODEL_PRESETS["tiny"]
    head = ReconHead(cfg).eval()
    f = torch.randn(2, cfg.bev_channels, *scale_shapes(cfg.grid)[2][1:]).narrow(2, 0, 4).narrow(3, 0, 4)
    outs = head.multi_scale(f)
    for (logit, off), shape in zip(outs, scale_shapes(cfg.grid), strict=True):
        assert logit.shape == (2, 1, *shape) and off.shape == (2, 3, *shape)
    occ, off = head(f)
    torch.testing.assert_close(occ, torch.sigmoid(outs[2][0]))
    half = torch.tensor(cfg.grid.voxel_size) / 2
    assert torch.all(off.abs() <= half.reshape(1, 3, 1, 1, 1))


def test_up2x_exports_as_one_conv_transpose_with_the_same_values():
    """The export form (ConvTranspose over [x, 1], the per-child bias as the ones channel's
    weights) is the torch form, and an export holds no 8-D Transpose."""
    import io

    import onnx

    torch.manual_seed(1)
    up = Up2x(5, 3).eval()
    x = torch.randn(1, 5, 3, 4, 6)
    torch.testing.assert_close(up.as_conv_transpose(x), up(x), atol=TOL, rtol=TOL)
    buf = io.BytesIO()
    with torch.no_grad():
        torch.onnx.export(up, (x,), buf, opset_version=19, dynamo=False)
    ops = [n.op_type for n in onnx.load_model_from_string(buf.getvalue()).graph.node]
    assert "ConvTranspose" in ops and "Transpose" not in ops
