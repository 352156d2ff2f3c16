"""Count the multiply-add FLOPs of an ONNX graph for concrete input shapes.

Counts ``2 x MACs`` of the compute-bound operators (Conv, ConvTranspose, DeformConv, MatMul,
Gemm); element-wise work is ignored, as in the usual "model FLOPs" figures. Shapes come from
``onnx.shape_inference`` after the dynamic input dims are fixed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
from onnx import shape_inference


def _dims(vi: onnx.ValueInfoProto) -> list[int] | None:
    dims = [d.dim_value if d.HasField("dim_value") else -1 for d in vi.type.tensor_type.shape.dim]
    return None if any(d <= 0 for d in dims) else dims


@dataclass(frozen=True)
class NodeFlops:
    """One compute-bound node of a graph at concrete input shapes."""

    name: str  # node name (or its first output)
    op: str  # Conv, ConvTranspose, DeformConv, MatMul or Gemm
    flops: int  # 2 x multiply-adds of one run
    out_shape: tuple[int, ...]  # its output's shape
    rules: str | None  # MatMul fed by a Gather whose indices are this graph input (a rulebook), else None


def node_flops(model_path: str | Path, input_shapes: dict[str, tuple[int, ...]]) -> list[NodeFlops]:
    """Every compute-bound node of the graph at ``input_shapes`` (name -> shape) whose shapes shape
    inference resolves, in graph order (a node whose sizes depend on values, e.g. after NonZero, is
    left out)."""
    model = onnx.load(str(model_path))
    for inp in model.graph.input:
        if inp.name in input_shapes:
            dims = inp.type.tensor_type.shape.dim
            for d, v in zip(dims, input_shapes[inp.name], strict=True):
                d.ClearField("dim_param")
                d.dim_value = int(v)
    inferred = shape_inference.infer_shapes(model, data_prop=True)  # through Shape->Reshape chains
    shapes: dict[str, list[int]] = {}
    for vi in [*inferred.graph.input, *inferred.graph.value_info, *inferred.graph.output]:
        dims = _dims(vi)
        if dims is not None:
            shapes[vi.name] = dims
    for init in inferred.graph.initializer:
        shapes[init.name] = list(init.dims)
    graph_inputs = {i.name for i in inferred.graph.input}
    producer = {o: n for n in inferred.graph.node for o in n.output}

    def rulebook(name: str) -> str | None:
        """The graph input a Gather feeding ``name`` (through Reshape / Transpose) indexes with."""
        node = producer.get(name)
        while node is not None and node.op_type in ("Reshape", "Transpose"):
            node = producer.get(node.input[0])
        if node is not None and node.op_type == "Gather" and node.input[1] in graph_inputs:
            return str(node.input[1])
        return None

    out: list[NodeFlops] = []
    for node in inferred.graph.node:
        shape = shapes.get(node.output[0]) if node.output else None
        flops, rules = None, None
        if node.op_type in ("Conv", "DeformConv") and shape is not None:
            w = shapes[node.input[1]]  # (C_out, C_in / group, k...)
            flops = 2 * int(np.prod(shape)) * int(np.prod(w[1:]))
        elif node.op_type == "ConvTranspose" and node.input[0] in shapes:
            w = shapes[node.input[1]]  # (C_in, C_out / group, k...)
            x = shapes[node.input[0]]  # (B, C_in, spatial...)
            flops = 2 * int(np.prod(x)) * int(np.prod(w[1:]))
        elif node.op_type in ("MatMul", "Gemm") and shape is not None and node.input[0] in shapes:
            a = shapes[node.input[0]]
            k = a[-2] if node.op_type == "Gemm" and _attr(node, "transA") else a[-1]
            flops = 2 * int(np.prod(shape)) * int(k)
            rules = rulebook(node.input[0]) if node.op_type == "MatMul" else None
        if flops is not None:
            name = node.name or node.output[0]
            out.append(NodeFlops(name, node.op_type, flops, tuple(int(d) for d in shape or ()), rules))
    return out


def graph_flops(model_path: str | Path, input_shapes: dict[str, tuple[int, ...]]) -> int:
    """FLOPs (2 x multiply-adds) of one run of the graph at ``input_shapes`` (name -> shape)."""
    return sum(n.flops for n in node_flops(model_path, input_shapes))


def _attr(node: onnx.NodeProto, name: str) -> int:
    for a in node.attribute:
        if a.name == name:
            return int(a.i)
    return 0
