"""``encoder.onnx`` in the pair form: the trained sparse encoder's weights, another graph.

The rulebook form (``training.nn.encoder.SparseEncoder`` traced) multiplies all 27 taps of every
output voxel, zero rows included. The pair form (``runtime.engine.pairs``) multiplies only real
neighbour pairs: per layer Gather -> one batched MatMul over the taps -> Split by tap, then per
tap ScatterND with reduction add into the layer's output rows (each tap's output rows are
distinct, so no update collides); the BEV collapse likewise per height, into the occupied BEV
cells. Standard ONNX ops only, opset 19; onnxruntime and OpenVINO both run it. The graph is
written from the module's tensors with ``onnx.helper`` (tracing would turn each scatter-add into
a dense zero tensor plus an Add). Its output equals the rulebook form's up to float summation
order (``tests/test_encoder_pairs.py``).

Cost: onnxruntime 1.32 copies a ScatterND's whole data tensor on every call (not in place), so
each tap costs a copy of the layer's output; OpenVINO does not. Measured on Astyx frames, 2
threads (``msdnet-bench encoders``, ``docs/latency.md``).
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from torch import Tensor, nn

from msdnet.runtime.engine.pairs import CENTRE, groups_of, layer_names
from msdnet.runtime.model import onnx_spec


class _Graph:
    """Nodes, initializers and unique names of the graph being written."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self._n = 0

    def const(self, value: np.ndarray, hint: str) -> str:
        name = f"{hint}_{self._n}"
        self._n += 1
        self.inits.append(numpy_helper.from_array(np.array(value, order="C"), name))  # 0-d stays 0-d
        return name

    def op(self, op_type: str, inputs: list[str], hint: str, **attrs: object) -> str:
        out = f"{hint}_{self._n}"
        self._n += 1
        self.nodes.append(helper.make_node(op_type, inputs, [out], name=out, **attrs))
        return out


def _array(t: object) -> np.ndarray:
    return t.detach().cpu().numpy().astype(np.float32)  # type: ignore[attr-defined]


def _norm_relu(g: _Graph, x: str, norm: nn.LayerNorm, hint: str) -> str:
    """LayerNorm over channels (the last axis), then ReLU."""
    y = g.op(
        "LayerNormalization",
        [x, g.const(_array(norm.weight), f"{hint}_ln_w"), g.const(_array(norm.bias), f"{hint}_ln_b")],
        f"{hint}_ln",
        axis=-1,
        epsilon=float(norm.eps),
    )
    return g.op("Relu", [y], f"{hint}_relu")


def _scatter_taps(
    g: _Graph, acc: str, x: str, weight: np.ndarray, groups: tuple[tuple[int, ...], ...], hint: str
) -> str:
    """``acc`` (rows + 1, C_out) plus every real pair of every tap group: per group the pairs input
    ``<hint>_pairs_<i>`` (2, taps, P) gathers rows of ``x`` (padded with a zero row), one batched
    MatMul with the taps' weights (taps, C_in, C_out), one Split by tap, then one ScatterND-add
    per tap into its output rows."""
    c_in = weight.shape[1]
    xp = g.op("Concat", [x, g.const(np.zeros((1, c_in), np.float32), f"{hint}_zero")], f"{hint}_xp", axis=0)
    zero, one, last = (g.const(np.array(v, np.int64), f"{hint}_i{v}") for v in (0, 1, -1))
    for i, taps in enumerate(groups):
        pairs = f"{hint}_pairs_{i}"
        rows_in = g.op("Gather", [pairs, zero], f"{pairs}_in", axis=0)  # (taps, P)
        rows_out = g.op("Gather", [pairs, one], f"{pairs}_out", axis=0)
        rows_out = g.op("Unsqueeze", [rows_out, last], f"{pairs}_u")  # (taps, P, 1)
        gathered = g.op("Gather", [xp, rows_in], f"{pairs}_x", axis=0)  # (taps, P, C_in)
        prod = g.op("MatMul", [gathered, g.const(weight[list(taps)], f"{pairs}_w")], f"{pairs}_y")
        ones = g.const(np.ones(len(taps), np.int64), f"{pairs}_split")
        parts = [f"{pairs}_y{a}" for a in range(len(taps))]  # (1, P, C_out) each
        rows = [f"{pairs}_o{a}" for a in range(len(taps))]  # (1, P, 1) each
        g.nodes.append(helper.make_node("Split", [prod, ones], parts, name=f"{pairs}_ys", axis=0))
        g.nodes.append(helper.make_node("Split", [rows_out, ones], rows, name=f"{pairs}_os", axis=0))
        for a in range(len(taps)):
            acc = g.op("ScatterND", [acc, rows[a], parts[a]], f"{pairs}_acc{a}", reduction="add")
    return acc


def _zeros_rows(g: _Graph, count: str, cols: int, hint: str) -> str:
    """(count + 1, cols) float zeros; ``count`` a (1,) int64 tensor."""
    plus = g.op("Add", [count, g.const(np.array([1], np.int64), f"{hint}_one")], f"{hint}_rows")
    shape = g.op(
        "Concat", [plus, g.const(np.array([cols], np.int64), f"{hint}_cols")], f"{hint}_shape", axis=0
    )
    value = numpy_helper.from_array(np.zeros(1, np.float32))
    return g.op("ConstantOfShape", [shape], f"{hint}_zeros", value=value)


def _drop_last_row(g: _Graph, acc: str, hint: str) -> str:
    starts, ends = (
        g.const(np.array([0], np.int64), f"{hint}_s"),
        g.const(np.array([-1], np.int64), f"{hint}_e"),
    )
    return g.op("Slice", [acc, starts, ends], f"{hint}_rows")


def pairs_encoder_model(encoder: nn.Module, levels: int = onnx_spec.NUM_DOWN) -> onnx.ModelProto:
    """The pair form of ``encoder`` (a ``SparseEncoder`` with ``levels`` down layers) as an ONNX
    model with the inputs and output of ``onnx_spec.encoder_pairs_spec(levels)``."""
    spec = onnx_spec.encoder_pairs_spec(levels)
    g = _Graph()
    counts = "voxel_counts"
    # VFE, as the rulebook form: normalised columns -> Linear -> LayerNorm -> ReLU
    shift, scale = _array(encoder.shift), _array(encoder.scale)
    x = g.op("Sub", ["voxel_features", g.const(shift, "vfe_shift")], "vfe_sub")
    x = g.op("Div", [x, g.const(scale, "vfe_scale")], "vfe_div")
    linear, norm = encoder.vfe[0], encoder.vfe[1]
    x = g.op(
        "Gemm",
        [x, g.const(_array(linear.weight), "vfe_w"), g.const(_array(linear.bias), "vfe_b")],
        "vfe",
        transB=1,
    )
    x = _norm_relu(g, x, norm, "vfe")
    for layer in layer_names(levels):
        kind, level = layer.split("_")
        block = encoder.subm[int(level)] if kind == "subm" else encoder.down[int(level) - 1]
        weight = _array(block.conv.weight)  # (27, C_in, C_out), tap-major
        c_out = weight.shape[2]
        if kind == "subm":  # the centre tap maps every voxel onto itself: a plain GEMM
            centre = g.op("MatMul", [x, g.const(weight[CENTRE], f"{layer}_wc")], f"{layer}_centre")
            zero_row = g.const(np.zeros((1, c_out), np.float32), f"{layer}_zrow")
            acc = g.op("Concat", [centre, zero_row], f"{layer}_acc", axis=0)
            groups = groups_of(layer)
        else:
            lv = g.const(np.array([int(level)], np.int64), f"{layer}_level")
            acc = _zeros_rows(g, g.op("Gather", [counts, lv], f"{layer}_count", axis=0), c_out, layer)
            groups = groups_of(layer)
        acc = _scatter_taps(g, acc, x, weight, groups, layer)
        x = g.op(
            "Add", [_drop_last_row(g, acc, layer), g.const(_array(block.conv.bias), f"{layer}_b")], layer
        )
        x = _norm_relu(g, x, block.norm, layer)
    # BEV collapse: the 1x1 conv over (C x D8) channels, one tap per height, into occupied cells
    d8, h8, w8 = (int(v) for v in encoder.bev_shape)
    conv = encoder.to_bev
    c_bev, c_last = int(conv.weight.shape[0]), int(encoder.out_channels)
    w = _array(conv.weight)[:, :, 0, 0].reshape(c_bev, c_last, d8).transpose(2, 1, 0)  # (D8, C, C_bev)
    cells = g.const(np.array([h8 * w8], np.int64), "bev_cells")
    acc = _zeros_rows(g, cells, c_bev, "bev")
    acc = _scatter_taps(g, acc, x, np.ascontiguousarray(w), (tuple(range(d8)),), "bev")
    # "bev_pairs_0" is the contract's "bev_pairs"
    y = g.op("Add", [_drop_last_row(g, acc, "bev"), g.const(_array(conv.bias), "bev_b")], "bev_add")
    y = g.op("Transpose", [y], "bev_t", perm=[1, 0])  # (C_bev, H8 * W8)
    shape = g.const(np.array([1, c_bev, h8, w8], np.int64), "bev_shape")
    g.nodes.append(helper.make_node("Reshape", [y, shape], ["bev_features"], name="bev_features"))
    for node in g.nodes:  # the contract names the BEV pairs input "bev_pairs"
        renamed = ["bev_pairs" if n == "bev_pairs_0" else n for n in node.input]
        del node.input[:]
        node.input.extend(renamed)
    inputs = [
        helper.make_tensor_value_info("voxel_features", TensorProto.FLOAT, ["V_0", encoder.in_features])
    ]
    inputs.append(helper.make_tensor_value_info("voxel_counts", TensorProto.INT64, [levels + 1]))
    for name in spec.inputs[2:]:
        taps = d8 if name == "bev_pairs" else _taps(name)
        inputs.append(
            helper.make_tensor_value_info(name, TensorProto.INT64, [2, taps, spec.dynamic_axes[name][2]])
        )
    output = helper.make_tensor_value_info("bev_features", TensorProto.FLOAT, [1, c_bev, h8, w8])
    graph = helper.make_graph(g.nodes, "encoder_pairs", inputs, [output], g.inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", onnx_spec.OPSET)])
    model.ir_version = 9
    onnx.checker.check_model(model)
    return model


def _taps(name: str) -> int:
    """Taps of the group a ``<layer>_pairs_<g>`` input feeds."""
    layer, group = name.rsplit("_pairs_", 1)
    return len(groups_of(layer)[int(group)])


def pairs_reference(
    encoder: nn.Module, feeds: dict[str, np.ndarray], levels: int = onnx_spec.NUM_DOWN
) -> Tensor:
    """The pair form in torch (``index_add_`` per tap) on the pair inputs ``feeds``
    (``runtime.engine.pairs.pair_feeds`` plus voxel_features) -> F^S (1, C_bev, H8, W8): the
    arithmetic the graph of :func:`pairs_encoder_model` runs."""
    import torch

    def conv(
        x: Tensor, weight: Tensor, acc: Tensor, groups: tuple[tuple[int, ...], ...], hint: str
    ) -> Tensor:
        xp = torch.cat([x, x.new_zeros(1, x.shape[1])])
        for i, taps in enumerate(groups):
            pairs = torch.from_numpy(feeds[hint if hint == "bev_pairs" else f"{hint}_pairs_{i}"])
            prod = torch.matmul(xp[pairs[0]], weight[list(taps)])  # (taps, P, C_out)
            for a in range(len(taps)):
                acc = acc.index_add(0, pairs[1, a], prod[a])
        return acc[:-1]

    with torch.no_grad():
        x = torch.from_numpy(feeds["voxel_features"])
        x = encoder.vfe((x - encoder.shift) / encoder.scale)
        counts = feeds["voxel_counts"]
        for layer in layer_names(levels):
            kind, level = layer.split("_")
            block = encoder.subm[int(level)] if kind == "subm" else encoder.down[int(level) - 1]
            w = block.conv.weight
            if kind == "subm":
                acc = torch.cat([x @ w[CENTRE], x.new_zeros(1, w.shape[2])])
            else:
                acc = x.new_zeros(int(counts[int(level)]) + 1, w.shape[2])
            x = torch.relu(block.norm(conv(x, w, acc, groups_of(layer), layer) + block.conv.bias))
        d8, h8, w8 = (int(v) for v in encoder.bev_shape)
        c_bev = encoder.to_bev.weight.shape[0]
        wz = encoder.to_bev.weight[:, :, 0, 0].reshape(c_bev, -1, d8).permute(2, 1, 0)  # (D8, C, C_bev)
        acc = x.new_zeros(h8 * w8 + 1, c_bev)
        y = conv(x, wz, acc, (tuple(range(d8)),), "bev_pairs") + encoder.to_bev.bias
        return y.t().reshape(1, c_bev, h8, w8)
