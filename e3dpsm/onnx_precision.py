"""The precision each Conv/MatMul/Gemm of a QDQ graph computes in, read off the graph.

What a quantiser *asked* for and what an artifact *does* can differ (the recurrent groups'
projections are never searched; a runtime reads what the graph holds), so this reads each
compute node's inputs: an input behind a DequantizeLinear has the width of that
DequantizeLinear's integer input (an initializer's dtype for weights, the producing
QuantizeLinear's zero point or `output_dtype` for activations); any other input is float.

Labels (cheapest first): `int8` (8-bit activations and weights), `int16` (16-bit
activations, 8-bit weights), `int16w16` (16-bit both), `float` (any data input in float);
another mix is named `a<bits>w<bits>`.
"""
from __future__ import annotations

from collections import Counter

import onnx
from onnx import TensorProto

COMPUTE_OPS: tuple[str, ...] = ("Conv", "MatMul", "Gemm")
CENSUS_ORDER: tuple[str, ...] = ("int8", "int16", "int16w16", "float")
_BITS = {TensorProto.INT8: 8, TensorProto.UINT8: 8, TensorProto.INT16: 16, TensorProto.UINT16: 16,
         TensorProto.INT4: 4, TensorProto.UINT4: 4, TensorProto.INT32: 32}


def _integer_bits(tensor: str, initializers: dict[str, onnx.TensorProto],
                  producers: dict[str, onnx.NodeProto]) -> int | None:
    """Bits of the integer tensor a DequantizeLinear reads; None when not an integer tensor."""
    if tensor in initializers:
        return _BITS.get(initializers[tensor].data_type)
    quantize = producers.get(tensor)
    if quantize is None or quantize.op_type != "QuantizeLinear":
        return None
    if len(quantize.input) > 2 and quantize.input[2] in initializers:
        return _BITS.get(initializers[quantize.input[2]].data_type)
    for attr in quantize.attribute:
        if attr.name == "output_dtype" and attr.i:
            return _BITS.get(attr.i)
    return 8  # QuantizeLinear without a zero point writes uint8


def quantised_activation_bits(model: onnx.ModelProto) -> dict[str, int]:
    """{activation: bits} for every float activation a QuantizeLinear quantises (weights, which
    are initializers, left out)."""
    initializers = {init.name: init for init in model.graph.initializer}
    producers = {out: node for node in model.graph.node for out in node.output}
    bits = {node.input[0]: _integer_bits(node.output[0], initializers, producers)
            for node in model.graph.node if node.op_type == "QuantizeLinear" and node.input[0] not in initializers}
    return {tensor: b for tensor, b in bits.items() if b is not None}


def compute_precisions(model: onnx.ModelProto) -> dict[str, str]:
    """{node name: precision label} for every Conv/MatMul/Gemm (module doc)."""
    initializers = {init.name: init for init in model.graph.initializer}
    producers = {out: node for node in model.graph.node for out in node.output}
    labels: dict[str, str] = {}
    for node in model.graph.node:
        if node.op_type not in COMPUTE_OPS:
            continue
        activation_bits: list[int] = []
        weight_bits: list[int] = []
        is_float = False
        for tensor in node.input[:2]:  # data and weight; the bias follows the weight's scale
            dequantize = producers.get(tensor)
            bits = None
            if dequantize is not None and dequantize.op_type == "DequantizeLinear":
                bits = _integer_bits(dequantize.input[0], initializers, producers)
            if bits is None:
                is_float = True
            elif dequantize.input[0] in initializers:
                weight_bits.append(bits)
            else:
                activation_bits.append(bits)
        if is_float:
            labels[node.name] = "float"
            continue
        act = max(activation_bits)
        if not weight_bits:  # a MatMul of two activations (attention): no weights to widen
            labels[node.name] = {8: "int8", 16: "int16"}.get(act, f"a{act}")
            continue
        weight = max(weight_bits)
        labels[node.name] = {(8, 8): "int8", (16, 8): "int16", (16, 16): "int16w16"}.get((act, weight),
                                                                                        f"a{act}w{weight}")
    return labels


def precision_counts(precisions: dict[str, str]) -> dict[str, int]:
    """Nodes per label, in CENSUS_ORDER (other mixes after), zero counts included."""
    counts = Counter(precisions.values())
    ordered = {label: counts.get(label, 0) for label in CENSUS_ORDER}
    ordered.update({label: n for label, n in sorted(counts.items()) if label not in ordered})
    return ordered


def out_of_8_bits(precisions: dict[str, str]) -> int:
    """Compute nodes not at int8 (the 'nodes out of 8 bits' figure of the reports)."""
    return sum(1 for label in precisions.values() if label != "int8")
