"""FLOP counting of ONNX graphs against hand-computed counts; the machine description."""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from msdnet.benchmarks.flops import graph_flops
from msdnet.benchmarks.machine import machine_info


def test_conv_and_matmul_flops_by_hand(tmp_path):
    w = numpy_helper.from_array(np.zeros((8, 4, 3, 3), np.float32), "w")
    m = numpy_helper.from_array(np.zeros((8, 5), np.float32), "m")
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["y"], pads=[1, 1, 1, 1]),  # (1, 8, H, W)
        helper.make_node("Transpose", ["y"], ["yt"], perm=[0, 2, 3, 1]),  # (1, H, W, 8)
        helper.make_node("MatMul", ["yt", "m"], ["z"]),  # (1, H, W, 5)
    ]
    graph = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4, "H", "W"])],
        [helper.make_tensor_value_info("z", TensorProto.FLOAT, None)],
        [w, m],
    )
    path = tmp_path / "g.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 19)]), path)
    h, wd = 6, 10
    conv = 2 * (8 * h * wd) * (4 * 3 * 3)
    matmul = 2 * (h * wd * 5) * 8
    assert graph_flops(path, {"x": (1, 4, h, wd)}) == conv + matmul


def test_machine_info_without_sgemm():
    info = machine_info(sgemm=False)
    assert info.logical_cores >= 1 and "CPUExecutionProvider" in info.providers
