"""Find tensors stored outside an ONNX file (external data), without the ``onnx`` package.

The runtime must refuse graphs whose weights live in other files: they escape the manifest's
size + sha256 check. ``onnx`` is not a runtime dependency, but ``protobuf`` is (onnxruntime
needs it), so the few ``onnx.proto`` messages that can hold a tensor are declared here by field
number and parsed with protobuf itself; every other field is skipped as unknown. The field
numbers are checked against the real ``onnx`` descriptors in tests/test_export.py.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

_PKG = "msdnet_onnx_subset"
_EXTERNAL = 1  # TensorProto.DataLocation.EXTERNAL

# message -> [(field name, number, type name or scalar, repeated)]
SUBSET: dict[str, list[tuple[str, int, str, bool]]] = {
    "StringStringEntryProto": [("key", 1, "string", False), ("value", 2, "string", False)],
    "TensorProto": [
        ("name", 8, "string", False),
        ("external_data", 13, "StringStringEntryProto", True),
        ("data_location", 14, "int32", False),
    ],
    "SparseTensorProto": [("values", 1, "TensorProto", False), ("indices", 2, "TensorProto", False)],
    "AttributeProto": [
        ("t", 5, "TensorProto", False),
        ("g", 6, "GraphProto", False),
        ("tensors", 10, "TensorProto", True),
        ("graphs", 11, "GraphProto", True),
        ("sparse_tensor", 22, "SparseTensorProto", False),
        ("sparse_tensors", 23, "SparseTensorProto", True),
    ],
    "NodeProto": [("attribute", 5, "AttributeProto", True)],
    "ValueInfoProto": [("name", 1, "string", False)],
    "GraphProto": [
        ("node", 1, "NodeProto", True),
        ("initializer", 5, "TensorProto", True),
        ("input", 11, "ValueInfoProto", True),
        ("sparse_initializer", 15, "SparseTensorProto", True),
    ],
    "FunctionProto": [("node", 7, "NodeProto", True)],
    "TrainingInfoProto": [
        ("initialization", 1, "GraphProto", False),
        ("algorithm", 2, "GraphProto", False),
    ],
    "ModelProto": [
        ("graph", 7, "GraphProto", False),
        ("training_info", 20, "TrainingInfoProto", True),
        ("functions", 25, "FunctionProto", True),
    ],
}

_SCALARS = {
    "string": descriptor_pb2.FieldDescriptorProto.TYPE_STRING,
    "int32": descriptor_pb2.FieldDescriptorProto.TYPE_INT32,
}


@lru_cache(maxsize=1)
def _model_class() -> Any:
    """The protobuf class of the ``ModelProto`` subset, built once."""
    fdp = descriptor_pb2.FileDescriptorProto(name=f"{_PKG}.proto", package=_PKG, syntax="proto3")
    for msg_name, fields in SUBSET.items():
        msg = fdp.message_type.add(name=msg_name)
        for name, number, kind, repeated in fields:
            field = msg.field.add(name=name, number=number)
            field.label = (
                descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED
                if repeated
                else descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL
            )
            if kind in _SCALARS:
                field.type = _SCALARS[kind]
            else:
                field.type = descriptor_pb2.FieldDescriptorProto.TYPE_MESSAGE
                field.type_name = f".{_PKG}.{kind}"
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{_PKG}.ModelProto"))


def _graph_tensors(graph: Any) -> list[Any]:
    """Every TensorProto reachable from ``graph``: initializers, attributes, subgraphs."""
    out: list[Any] = list(graph.initializer)
    for sparse in graph.sparse_initializer:
        out += [sparse.values, sparse.indices]
    for node in graph.node:
        out += _node_tensors(node)
    return out


def _node_tensors(node: Any) -> list[Any]:
    out: list[Any] = []
    for attr in node.attribute:
        out += [attr.t, *attr.tensors]
        for sparse in [attr.sparse_tensor, *attr.sparse_tensors]:
            out += [sparse.values, sparse.indices]
        for sub in [attr.g, *attr.graphs]:
            out += _graph_tensors(sub)
    return out


def _parse(model: bytes) -> Any:
    proto = _model_class()()
    try:
        proto.ParseFromString(model)
    except Exception as err:  # protobuf's DecodeError and friends
        raise ValueError(f"not an ONNX model ({type(err).__name__})") from err
    return proto


def graph_inputs(model: bytes) -> tuple[str, ...]:
    """The names of the main graph's inputs in serialized ONNX ``model``, initializers listed as
    inputs (older IR versions) left out. Raises ``ValueError`` when the bytes are not ONNX."""
    graph = _parse(model).graph
    weights = {t.name for t in graph.initializer}
    return tuple(i.name for i in graph.input if i.name not in weights)


def external_tensors(model: bytes) -> list[str]:
    """Names of tensors in serialized ONNX ``model`` whose data lives in another file.

    Raises ``ValueError`` when the bytes are not a parseable ONNX model.
    """
    proto = _parse(model)
    tensors = _graph_tensors(proto.graph)
    for info in proto.training_info:
        tensors += _graph_tensors(info.initialization) + _graph_tensors(info.algorithm)
    for func in proto.functions:
        for node in func.node:
            tensors += _node_tensors(node)
    return [t.name or "<unnamed>" for t in tensors if t.data_location == _EXTERNAL or t.external_data]
