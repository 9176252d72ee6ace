"""Compute outputs left in float where no quantised op reads them (`quantize --float-outputs`).

ONNX Runtime's QDQ quantiser puts a Q/DQ pair on the output of each Conv, Gemm and MatMul it
quantises, whether or not a quantised op reads that output. Where none does (the output goes
to a residual Add, a LayerNormalization, a head's Mul, all float in this graph), the pair
only rounds the result to 8 bits before float code reads it: it buys ONNX Runtime a fused
kernel with an 8-bit output (QLinearConv, QLinearMatMul), and costs accuracy. What each
Conv/MatMul/Gemm *reads* is unchanged (8-bit weights and activations; census.py), so a node
stays an 8-bit node; its int32 accumulator is dequantised instead of requantised.

What each choice cost on `small`: benchmarks/results/quantize_history.md ("The full-integer
graph: the carried state, and outputs nothing quantised reads").
"""
from __future__ import annotations

from typing import Iterable

import onnx

from e3dpsm.onnx_graph import drop_unused_initializers
from e3dpsm.onnx_precision import COMPUTE_OPS

# "matmul": MatMul and Gemm outputs (no speed cost on ONNX Runtime); "all": Conv outputs too.
FLOAT_OUTPUTS: dict[str, tuple[str, ...]] = {"none": (), "matmul": ("MatMul", "Gemm"), "all": COMPUTE_OPS}
# Ops that move data without computing: a Q/DQ pair behind one of them still feeds whatever
# reads its output (ONNX Runtime quantises a 2-D Gemm's Reshapes with it).
_DATA_MOVEMENT = frozenset({"Reshape", "Transpose", "Flatten", "Squeeze", "Unsqueeze", "Identity"})


def dequantised_outputs(model: onnx.ModelProto, op_types: Iterable[str],
                        quantised_ops: Iterable[str] = COMPUTE_OPS) -> list[str]:
    """Remove, in place, the Q/DQ pair on each output of an `op_types` node that no quantised
    op reads (no QuantizeLinear or `quantised_ops` node after it, through data-movement ops:
    the quantiser's op types, so that under `--int8-elementwise` an Add or Mul between two
    convolutions keeps its 8-bit input); returns the names of the nodes whose output is now
    float. A pair on a graph output is kept (its name is part of the interface)."""
    wanted = set(op_types)
    quantised = set(quantised_ops) | {"QuantizeLinear"}
    if not wanted:
        return []
    producers = {out: node for node in model.graph.node for out in node.output}
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    graph_outputs = {o.name for o in model.graph.output}

    def read_quantised(tensor: str) -> bool:
        for reader in consumers.get(tensor, []):
            if reader.op_type in quantised:
                return True
            if reader.op_type in _DATA_MOVEMENT and any(read_quantised(o) for o in reader.output):
                return True
        return tensor in graph_outputs

    removed: set[int] = set()
    nodes: list[str] = []
    for quantize in model.graph.node:
        if quantize.op_type != "QuantizeLinear":
            continue
        producer = producers.get(quantize.input[0])
        if producer is None or producer.op_type not in wanted:
            continue
        dequantizers = consumers.get(quantize.output[0], [])
        if not dequantizers or any(d.op_type != "DequantizeLinear" for d in dequantizers) \
                or quantize.output[0] in graph_outputs:
            continue
        if any(read_quantised(d.output[0]) for d in dequantizers):
            continue
        for dequantize in dequantizers:
            for reader in consumers.get(dequantize.output[0], []):
                for i, name in enumerate(reader.input):
                    if name == dequantize.output[0]:
                        reader.input[i] = quantize.input[0]
            removed.add(id(dequantize))
        removed.add(id(quantize))
        nodes.append(producer.name)
    freed = {name for node in model.graph.node if id(node) in removed for name in node.input[1:]}
    kept = [n for n in model.graph.node if id(n) not in removed]
    del model.graph.node[:]
    model.graph.node.extend(kept)
    drop_unused_initializers(model, among=freed)
    return nodes
