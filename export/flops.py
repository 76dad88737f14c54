"""FLOPs of an ONNX graph, counted from the graph itself (imports only onnx and numpy).

Counts the multiply–accumulates of Conv, ConvTranspose, MatMul and Gemm from
shapes given by ONNX shape inference, and reports FLOPs = 2 · MACs (bias adds,
BN, activations and resizes are ignored: they are a rounding error next to the
convolutions). The runtime may import this module: it has no torch dependency.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnx
from onnx import shape_inference

COUNTED_OPS = ("Conv", "ConvTranspose", "MatMul", "Gemm")


@dataclass
class FlopCount:
    """FLOPs (2 · MACs) of a graph, in total and per operator type."""

    total: int = 0
    by_op: dict[str, int] = field(default_factory=dict)
    nodes: int = 0  # counted nodes

    @property
    def gflops(self) -> float:
        return self.total / 1e9


def _static_shapes(model: onnx.ModelProto) -> dict[str, tuple[int, ...]]:
    """Name → static shape of every tensor whose shape is fully known after inference."""
    shapes: dict[str, tuple[int, ...]] = {}
    for init in model.graph.initializer:
        shapes[init.name] = tuple(int(d) for d in init.dims)
    graph = model.graph
    for value in list(graph.input) + list(graph.value_info) + list(graph.output):
        dims = value.type.tensor_type.shape.dim
        if value.type.tensor_type.HasField("shape") and all(d.HasField("dim_value") for d in dims):
            shapes[value.name] = tuple(int(d.dim_value) for d in dims)
    return shapes


def _attribute(node: onnx.NodeProto, name: str, default: int) -> int:
    for attr in node.attribute:
        if attr.name == name:
            return int(onnx.helper.get_attribute_value(attr))
    return default


def _node_macs(node: onnx.NodeProto, shapes: dict[str, tuple[int, ...]]) -> int:
    """Multiply–accumulates of one counted node; raises ValueError if a shape is unknown."""

    def shape(name: str) -> tuple[int, ...]:
        if name not in shapes:
            raise ValueError(f"{node.op_type} node {node.name!r}: shape of {name!r} is unknown (dynamic graph?)")
        return shapes[name]

    if node.op_type == "Conv":
        weight = shape(node.input[1])  # (C_out, C_in / group, k…)
        out = shape(node.output[0])  # (N, C_out, spatial…)
        return int(np.prod(out, dtype=np.int64)) * int(np.prod(weight[1:], dtype=np.int64))
    if node.op_type == "ConvTranspose":
        weight = shape(node.input[1])  # (C_in, C_out / group, k…)
        inp = shape(node.input[0])  # (N, C_in, spatial…)
        # Every input element scatters into C_out/group · prod(k) outputs.
        return int(np.prod(inp, dtype=np.int64)) * int(np.prod(weight[1:], dtype=np.int64))
    if node.op_type == "MatMul":
        a = shape(node.input[0])  # (…, M, K) or (K,)
        out = shape(node.output[0])  # (…, M, N): each output element is a K-long dot product
        return int(np.prod(out, dtype=np.int64)) * int(a[-1])
    if node.op_type == "Gemm":
        a = shape(node.input[0])
        out = shape(node.output[0])
        k = a[0] if _attribute(node, "transA", 0) else a[1]
        return int(np.prod(out, dtype=np.int64)) * int(k)
    return 0


def count_flops(model: onnx.ModelProto | str | Path) -> FlopCount:
    """FLOPs (2 · MACs) of Conv/ConvTranspose/MatMul/Gemm in an ONNX model or file.

    The graph must have static shapes (every counted tensor's shape known after
    ``onnx.shape_inference``); a dynamic dimension raises ValueError naming the node.
    """
    if not isinstance(model, onnx.ModelProto):
        model = onnx.load(str(model))
    inferred = shape_inference.infer_shapes(model)
    shapes = _static_shapes(inferred)
    result = FlopCount()
    for node in inferred.graph.node:
        if node.op_type not in COUNTED_OPS:
            continue
        flops = 2 * _node_macs(node, shapes)
        result.total += flops
        result.by_op[node.op_type] = result.by_op.get(node.op_type, 0) + flops
        result.nodes += 1
    return result
