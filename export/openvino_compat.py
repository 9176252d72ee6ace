"""Quantised graphs that OpenVINO's CPU plugin compiles, and computes as ONNX Runtime does.

OpenVINO's low precision transformations (LPT) move the dequantisation of an 8-bit product
(MatMul, Gemm) to after it, as a Multiply by the activation scale times the weights'
per-channel scales, and then push that Multiply on through precision-preserving operators.
Their ReshapeTransformation (src/common/low_precision_transformations/src/reshape.cpp in
https://github.com/openvinotoolkit/openvino; the same logic in its 2023 and 2025 sources, and
2026.4 behaves so) lets a per-channel Multiply through a Reshape when the Reshape keeps the
first axis and the new second axis is at least the channel count. Two dynamic axes compare
equal there, and the check that the new second axis is a multiple of the channel count runs
on static shapes only.

onnxsim rewrites a Linear over tokens (MatMul + Add on [batch, tokens, C]) as a 2-D Gemm on
[batch * tokens, C] between two Reshapes, and merges the second with the next Reshape:
`paper`'s value projection reads Gemm [?, 32] -> Reshape [-1, 48, 64, 4, 8]. Both first axes
are dynamic, so LPT takes 48 for the channel axis and lays the 32 scales along it:
- 48 is no multiple of 32: compiling fails ("Requested output shape [1,48,1,1,1] is
  incompatible with input shape", on the [1, 32] scales);
- a multiple (Gemm [?, 16] -> Reshape [-1, 32, 16]): it compiles and scales row r of the 32
  by channel r % 16's scale, silently wrong.
Only where the Multiply meets the Reshape: a Gemm without a bias, or with a zero bias, which
OpenVINO folds away (a fresh model's attention value projection and direct pose head); a
non-zero bias's Add sits between them and stops the pattern. The guard goes in either way:
what reaches the Reshape is OpenVINO's choice, and ONNX Runtime's numbers do not change.

The guard: a Reshape to [1, -1, C] between the product and that Reshape. LPT lets no
per-channel Multiply through a Reshape whose new second axis is dynamic, so the scales stay
on the product's [rows, C] output, where they are right; the next Reshape then has no
dequantisation before it. ONNX Runtime computes the same numbers: a Reshape moves no value.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
import onnx.numpy_helper

from e3dpsm.onnx_graph import GraphIndex, drop_unused_initializers, node_key

GUARD_SUFFIX = "/openvino_row_guard"
_PRODUCTS = ("Gemm", "MatMul")


@dataclass(frozen=True)
class RowSplit:
    """A Reshape that splits the rows of a per-channel dequantised 2-D product."""

    reshape: str  # node key (e3dpsm.onnx_graph.node_key)
    channels: int  # the product's output channels, its second axis
    target: tuple[int, ...]  # the Reshape's shape, 0 ("copy this axis") resolved
    copies: bool = False  # the written shape has a 0


def openvino_compatible(model: onnx.ModelProto) -> list[str]:
    """Guard, in place, every Reshape OpenVINO's LPT would misread (module docstring) with
    a Reshape to [1, -1, C] before it; returns the guarded Reshapes' node keys. Idempotent:
    a guarded Reshape no longer reads a product."""
    splits = row_splitting_reshapes(model)
    graph = model.graph
    for split in splits:
        position, reshape = next((i, n) for i, n in enumerate(graph.node) if node_key(n) == split.reshape)
        guard = f"{split.reshape}{GUARD_SUFFIX}"
        shape = _add_initializer(graph, f"{guard}/shape", [1, -1, split.channels])
        graph.node.insert(position, onnx.helper.make_node("Reshape", [reshape.input[0], shape],
                                                          [f"{guard}/output"], name=guard))
        reshape.input[0] = f"{guard}/output"
        if split.copies:  # a 0 copied an axis of the 2-D input; after the guard it would copy the guard's
            reshape.input[1] = _add_initializer(graph, f"{guard}/target", list(split.target))
    return [s.reshape for s in splits]


def remove_guards(model: onnx.ModelProto) -> list[str]:
    """Take the guards out again, in place (the graph as OpenVINO fails on it: tests and
    benchmarks/bench_openvino_int8.py); returns their node names. A target whose 0 a guard
    wrote out stays written out: for the 2-D input it means the same."""
    graph = model.graph
    guards = {n.name: (n.input[0], n.input[1], n.output[0]) for n in graph.node
              if n.op_type == "Reshape" and n.name.endswith(GUARD_SUFFIX)}
    bypass = {output: source for source, _, output in guards.values()}
    kept = [n for n in graph.node if n.name not in guards]
    for node in kept:
        node.input[:] = [bypass.get(name, name) for name in node.input]
    del graph.node[:]
    graph.node.extend(kept)
    drop_unused_initializers(model, among=[shape for _, shape, _ in guards.values()])
    return list(guards)


def row_splitting_reshapes(model: onnx.ModelProto) -> list[RowSplit]:
    """The Reshapes LPT would let a per-channel dequantisation through wrongly: fed by a
    Gemm or MatMul whose inputs are both dequantised, the weights per channel, on a 2-D
    [rows, C] output with dynamic rows, to a constant shape [-1, d1, ...] with d1 >= C
    that splits the rows (d1 * ... != C)."""
    index = GraphIndex(model)
    constants = _constants(model)
    shapes = _inferred_shapes(model)
    found = []
    for key, node in index.nodes.items():
        if node.op_type != "Reshape" or len(node.input) < 2 or node.input[1] not in constants or _allows_zero(node):
            continue
        product = index.nodes.get(index.producer.get(node.input[0], ""))
        channels = _per_channel_channels(index, constants, product)
        if channels is None or not _dynamic_rows(shapes.get(node.input[0]), product):
            continue
        written = [int(v) for v in onnx.numpy_helper.to_array(constants[node.input[1]]).reshape(-1)]
        target = _resolve_copies(written, channels)
        if target is not None and _splits_rows(target, channels):
            found.append(RowSplit(key, channels, tuple(target), copies=0 in written))
    return found


def _per_channel_channels(index: GraphIndex, constants: dict[str, onnx.TensorProto],
                          product: onnx.NodeProto | None) -> int | None:
    """The output channels of `product` if it is a Gemm / MatMul whose two inputs come out
    of DequantizeLinear, the weights' with per-channel scales; otherwise None."""
    if product is None or product.op_type not in _PRODUCTS:
        return None
    dequantized = [index.nodes.get(index.producer.get(t, "")) for t in product.input[:2]]
    if any(d is None or d.op_type != "DequantizeLinear" for d in dequantized):
        return None
    weights, scales = (constants.get(t) for t in dequantized[1].input[:2])
    if weights is None or scales is None or int(np.prod(scales.dims)) < 2 or len(weights.dims) != 2:
        return None
    transposed = product.op_type == "Gemm" and _attribute(product, "transB", 0) == 1
    return int(weights.dims[0] if transposed else weights.dims[1])


def _dynamic_rows(shape: list[int | None] | None, product: onnx.NodeProto) -> bool:
    """A 2-D product whose rows are not a fixed number; of unknown shape, a Gemm (always
    2-D) counts, a MatMul (any rank) does not."""
    if shape is None:
        return product.op_type == "Gemm"
    return len(shape) == 2 and shape[0] is None


def _resolve_copies(target: list[int], channels: int) -> list[int] | None:
    """The shape with Reshape's 0 ("copy the input's axis") replaced for a [rows, C] input;
    None where a 0 copies the rows (the rows then stay whole) or an axis the input lacks."""
    resolved = []
    for axis, size in enumerate(target):
        if size != 0:
            resolved.append(size)
        elif axis == 1:
            resolved.append(channels)
        else:
            return None
    return resolved


def _splits_rows(target: list[int], channels: int) -> bool:
    """[-1, d1, ...] with d1 >= C whose trailing axes do not hold exactly one row's C values."""
    if len(target) < 2 or target[0] != -1 or target[1] < channels:
        return False
    return int(np.prod(target[1:])) != channels


def _allows_zero(node: onnx.NodeProto) -> bool:
    return _attribute(node, "allowzero", 0) == 1


def _attribute(node: onnx.NodeProto, name: str, default: int) -> int:
    return next((onnx.helper.get_attribute_value(a) for a in node.attribute if a.name == name), default)


def _constants(model: onnx.ModelProto) -> dict[str, onnx.TensorProto]:
    """Initializers and Constant nodes' tensors by name (read lazily: only shapes are converted)."""
    tensors = {init.name: init for init in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "Constant" and node.attribute and node.attribute[0].name == "value":
            tensors[node.output[0]] = node.attribute[0].t
    return tensors


def _inferred_shapes(model: onnx.ModelProto) -> dict[str, list[int | None]]:
    """Tensor -> axis sizes as ONNX shape inference tells them, None for a symbolic axis."""
    inferred = onnx.shape_inference.infer_shapes(model)
    shapes = {}
    for value in (*inferred.graph.input, *inferred.graph.output, *inferred.graph.value_info):
        tensor_type = value.type.tensor_type
        if tensor_type.HasField("shape"):
            shapes[value.name] = [d.dim_value if d.HasField("dim_value") else None for d in tensor_type.shape.dim]
    return shapes


def _add_initializer(graph: onnx.GraphProto, name: str, values: list[int]) -> str:
    graph.initializer.append(onnx.numpy_helper.from_array(np.asarray(values, dtype=np.int64), name))
    return name
