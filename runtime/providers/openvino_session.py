"""An OpenVINO-backed graph with the slice of onnxruntime's session API the Pipeline uses.

``--provider openvino`` (``runtime.providers.session.create_session``) runs every graph OpenVINO can load
through :class:`OpenVinoSession`; the others (``rgfd_adapter.onnx``: no DeformConv in OpenVINO's
ONNX front end) stay on onnxruntime's CPU provider. The Pipeline binds its buffers as OrtValues
either way: :class:`OvBinding` reads bound inputs from them and writes outputs into them, so the
pipeline code is the same for both engines. Needs the optional ``[openvino]`` extra.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import onnxruntime as ort


@dataclass(frozen=True)
class NodeArg:
    """Name and shape of a graph input or output (ints; a string for a dynamic dimension)."""

    name: str
    shape: list[int | str]


def _node_arg(port: Any) -> NodeArg:
    dims = [d.get_length() if d.is_static else f"d{i}" for i, d in enumerate(port.get_partial_shape())]
    return NodeArg(port.get_any_name(), dims)


class OvBinding:
    """IOBinding look-alike: inputs from OrtValues or host arrays, outputs into OrtValues or new ones."""

    def __init__(self, session: OpenVinoSession) -> None:
        self._session = session
        self._inputs: dict[str, Any] = {}
        self._out_values: dict[str, ort.OrtValue] = {}  # bound by the caller: written in place
        self._results: dict[str, np.ndarray] = {}  # outputs of the last run

    def bind_ortvalue_input(self, name: str, value: ort.OrtValue) -> None:
        self._inputs[name] = value

    def bind_cpu_input(self, name: str, array: np.ndarray) -> None:
        self._inputs[name] = array

    def bind_ortvalue_output(self, name: str, value: ort.OrtValue) -> None:
        self._out_values[name] = value

    def bind_output(self, name: str, device_type: str = "cpu", device_id: int = 0) -> None:
        self._out_values.pop(name, None)  # allocated per run, like onnxruntime's

    def clear_binding_outputs(self) -> None:
        self._out_values.clear()

    def feeds(self) -> dict[str, np.ndarray]:
        return {k: v.numpy() if isinstance(v, ort.OrtValue) else v for k, v in self._inputs.items()}

    def store(self, outputs: dict[str, np.ndarray]) -> None:
        for name, arr in outputs.items():
            if name in self._out_values:
                self._out_values[name].update_inplace(np.ascontiguousarray(arr))
        self._results = outputs

    def get_outputs(self) -> list[ort.OrtValue]:
        """The last run's outputs as OrtValues (host memory), in graph order."""
        out = []
        for o in self._session.get_outputs():
            bound = self._out_values.get(o.name)
            out.append(
                bound if bound is not None else ort.OrtValue.ortvalue_from_numpy(self._results[o.name])
            )
        return out


class OpenVinoSession:
    """One ONNX graph compiled by OpenVINO for the CPU with ``threads`` inference threads."""

    def __init__(self, model: bytes, threads: int | None = None, precision: str = "f32") -> None:
        """``precision``: ``f32``, or ``bf16`` (OpenVINO's inference precision hint; f32 in and out)."""
        import openvino as ov

        if precision not in ("f32", "bf16"):
            raise ValueError(f"precision must be f32 or bf16, got {precision!r}")
        self.precision = precision

        core = ov.Core()
        read = core.read_model(model)  # raises on ops its ONNX front end cannot convert
        self._inputs = [_node_arg(p) for p in read.inputs]  # ONNX names, before compilation renames
        self._outputs = [_node_arg(p) for p in read.outputs]
        # f32 unless asked: on CPUs with bf16 units OpenVINO would otherwise compute in bf16
        config: dict[str, Any] = {
            "PERFORMANCE_HINT": "LATENCY",
            "NUM_STREAMS": 1,
            "INFERENCE_PRECISION_HINT": precision,
        }
        if threads is not None:
            config["INFERENCE_NUM_THREADS"] = int(threads)
        self._compiled = core.compile_model(read, "CPU", config)
        self._request = self._compiled.create_infer_request()

    def get_inputs(self) -> list[NodeArg]:
        return self._inputs

    def get_outputs(self) -> list[NodeArg]:
        return self._outputs

    def get_providers(self) -> list[str]:
        return ["OpenVINO" if self.precision == "f32" else "OpenVINO-bf16"]

    def _infer(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        ordered = [np.ascontiguousarray(feeds[i.name]) for i in self._inputs]  # by position
        self._request.infer(ordered)
        return {o.name: self._request.get_output_tensor(k).data.copy() for k, o in enumerate(self._outputs)}

    def run(self, output_names: list[str] | None, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        out = self._infer(feeds)
        return [out[n] for n in (output_names or [o.name for o in self._outputs])]

    def io_binding(self) -> OvBinding:
        return OvBinding(self)

    def run_with_iobinding(self, binding: OvBinding, run_options: Any = None) -> None:
        binding.store(self._infer(binding.feeds()))
