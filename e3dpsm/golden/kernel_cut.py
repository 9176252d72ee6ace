"""Graph surgery for the kernel-parity trace (kernel_trace.py): expose every quantised
activation of a QDQ graph, and cut the graph at them.

A QDQ graph quantises an activation as `x -> QuantizeLinear -> q (u8) -> DequantizeLinear`;
ONNX Runtime fuses `DQ -> Conv/MatMul/Gemm -> Q` into one integer kernel whose output is `q`.
Exposing `q` as a graph output leaves those fusions intact (the tensor exists either way),
unlike exposing a float tensor between DQ and Q. Cutting the graph at every `q` (its
consumers read a new graph input `q` + FEED_SUFFIX instead) makes each segment, from the
quantised activations it reads to the one it writes, compute from values fed to it: fed
the host's codes, a device's segment shows only its own arithmetic's departures, none
propagated from upstream.
"""
from __future__ import annotations

import onnx
from onnx import TensorProto, helper

from e3dpsm.golden.kernel_trace import FEED_SUFFIX
from e3dpsm.onnx_graph import drop_unused_initializers, with_outputs
# Ops ONNX Runtime runs as one integer kernel between DequantizeLinear and QuantizeLinear
# (QLinearConv, QLinearMatMul, QGemm); a segment of one of these alone is integer arithmetic
# plus requantisation.
INTEGER_FUSED_OPS = ("Conv", "MatMul", "Gemm")
# Left out of a segment's description: the Q/DQ pair itself and shape bookkeeping.
BOOKKEEPING_OPS = frozenset({"QuantizeLinear", "DequantizeLinear", "Shape", "Constant", "ConstantOfShape",
                             "Identity", "Reshape", "Unsqueeze", "Squeeze", "Transpose", "Gather", "Concat", "Slice"})


def quantized_activations(model: onnx.ModelProto) -> list[str]:
    """Outputs of the QuantizeLinear nodes that quantise a computed tensor (not a constant),
    in graph order."""
    constants = {i.name for i in model.graph.initializer}
    constants |= {o for n in model.graph.node if n.op_type == "Constant" for o in n.output}
    return [n.output[0] for n in model.graph.node
            if n.op_type == "QuantizeLinear" and n.input[0] not in constants]


def expose_quantized(model: onnx.ModelProto) -> tuple[onnx.ModelProto, list[str]]:
    """A copy of `model` that also outputs every quantised activation; with their names."""
    names = quantized_activations(model)
    if not names:
        raise ValueError("the graph has no QuantizeLinear on a computed tensor: not a QDQ graph")
    return with_outputs(model, names), names


def cut_at_quantized(model: onnx.ModelProto) -> tuple[onnx.ModelProto, list[str]]:
    """A copy of `model`, quantised activations exposed, whose consumers of each quantised
    activation `q` read the graph input `q` + FEED_SUFFIX instead (same element type)."""
    cut, names = expose_quantized(model)
    dtypes = _code_types(model)
    for node in cut.graph.node:  # a QuantizeLinear reads a float tensor, never a code: only readers change
        for i, name in enumerate(node.input):
            if name in dtypes:
                node.input[i] = name + FEED_SUFFIX
    read = {i for n in cut.graph.node for i in n.input}
    for name in names:
        if name + FEED_SUFFIX in read:
            cut.graph.input.append(helper.make_tensor_value_info(name + FEED_SUFFIX, dtypes[name], None))
    return cut, names


def _code_types(model: onnx.ModelProto) -> dict[str, int]:
    """Quantised activation -> its element type (the zero point's; uint8 without one)."""
    initializers = {i.name: i.data_type for i in model.graph.initializer}
    constants = {i.name for i in model.graph.initializer}
    return {n.output[0]: initializers.get(n.input[2], TensorProto.UINT8) if len(n.input) > 2 else TensorProto.UINT8
            for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] not in constants}


FLOAT_SUFFIX = " (float)"  # a Conv/MatMul/Gemm with an operand not dequantised runs as a float kernel


def segment_ops(model: onnx.ModelProto) -> dict[str, list[str]]:
    """Quantised activation -> the op types of its segment: the nodes between the quantised
    activations (or graph inputs, constants) it depends on and its QuantizeLinear, in graph
    order, DequantizeLinear and QuantizeLinear left out. A Conv, MatMul or Gemm with an operand
    that is not a DequantizeLinear output (a float tensor, a float weight or bias) is not fused
    into an integer kernel: it is described as, e.g., `MatMul (float)`."""
    producer = {o: n for n in model.graph.node for o in n.output}

    def describe(node: onnx.NodeProto) -> str:
        # ONNX Runtime fuses DQ -> op -> Q into an integer kernel when its operands (activation,
        # weight, and the int32 bias the quantizer writes) are DequantizeLinear outputs; anything
        # else is taken for a float kernel, so that what is called portable surely is.
        float_input = any(name not in producer or producer[name].op_type != "DequantizeLinear"
                          for name in node.input if name)
        return node.op_type + FLOAT_SUFFIX if node.op_type in INTEGER_FUSED_OPS and float_input else node.op_type

    order = {id(n): i for i, n in enumerate(model.graph.node)}
    codes = set(quantized_activations(model))
    segments: dict[str, list[str]] = {}
    for q in codes:
        seen: dict[int, onnx.NodeProto] = {}
        stack = [producer[q]]
        while stack:
            node = stack.pop()
            if id(node) in seen:
                continue
            seen[id(node)] = node
            for name in node.input:
                if name not in codes and name in producer:  # a segment ends at the codes it reads
                    stack.append(producer[name])
        nodes = sorted(seen.values(), key=lambda n: order[id(n)])
        segments[q] = [describe(n) for n in nodes if n.op_type not in BOOKKEEPING_OPS]
    return segments


def integer_only(ops: list[str]) -> bool:
    """A segment that is one fused integer kernel (Conv/MatMul/Gemm and requantisation)."""
    return len(ops) == 1 and ops[0] in INTEGER_FUSED_OPS


# Float ops whose every element is one IEEE operation on its inputs: ONNX Runtime computes
# them to the bit on any ISA. Reductions (LayerNormalization, Softmax), transcendental
# approximations (Sigmoid, Erf, Exp) and fused multiply-adds (BatchNormalization) are not.
EXACT_FLOAT_OPS = frozenset({"Add", "Sub", "Mul", "Div", "Relu", "Max", "Min", "Neg", "Abs", "Where", "Equal",
                             "Expand", "Tile", "Pad", "MaxPool"})


def portable_segment(ops: list[str], allowed: frozenset[str] = EXACT_FLOAT_OPS) -> bool:
    """A segment that computes the same codes on any ISA: integer kernels and `allowed` float ops."""
    return all(op in INTEGER_FUSED_OPS or op in allowed for op in ops)


def drop_quantization(model: onnx.ModelProto, codes: set[str]) -> int:
    """Remove, in place, the `Q -> q -> DQ` pairs of the named codes (their consumers read the
    float tensor instead); a code read by anything but DequantizeLinear, or leaving the graph,
    is kept. Returns how many were removed."""
    readers: dict[str, list[onnx.NodeProto]] = {}
    for node in model.graph.node:
        for name in node.input:
            readers.setdefault(name, []).append(node)
    outputs = {o.name for o in model.graph.output}
    rename: dict[str, str] = {}
    dropped: set[int] = set()
    for node in model.graph.node:
        q = node.output[0] if node.op_type == "QuantizeLinear" else None
        if q not in codes or q in outputs or any(r.op_type != "DequantizeLinear" for r in readers.get(q, [])):
            continue
        dropped.add(id(node))
        for dq in readers.get(q, []):
            dropped.add(id(dq))
            rename[dq.output[0]] = node.input[0]
    kept = [n for n in model.graph.node if id(n) not in dropped]
    for node in kept:
        for i, name in enumerate(node.input):
            node.input[i] = rename.get(name, name)
    for output in model.graph.output:
        output.name = rename.get(output.name, output.name)
    del model.graph.node[:]
    model.graph.node.extend(kept)
    return len(dropped) - len(rename)  # the QuantizeLinear nodes among them


def portable_qdq(model: onnx.ModelProto, allowed: frozenset[str] = EXACT_FLOAT_OPS
                 ) -> tuple[onnx.ModelProto, list[str]]:
    """A copy of `model` that keeps only the quantised activations whose segments are portable:
    the others' Q/DQ pairs are removed (those activations stay float, the weights stay 8-bit),
    until every remaining segment is portable. Returns it and the codes removed."""
    portable = onnx.ModelProto()
    portable.CopyFrom(model)
    removed: list[str] = []
    while True:
        segments = segment_ops(portable)
        drop = {q for q, ops in segments.items() if not portable_segment(ops, allowed)}
        if not drop or not drop_quantization(portable, drop):
            drop_unused_initializers(portable)
            return portable, removed
        removed += sorted(drop - set(quantized_activations(portable)))
