"""`quantize --mode int8-weights`: the step graph's weights stored in 8 bits, its arithmetic
float: the ONNX counterpart of `convert litert --quantize int8-weights` (docs/edge.md#int8-for-arm).

Every Conv, Gemm and MatMul whose weight is an initializer reads it as
`Cast(int8 codes) * per-channel scale`: symmetric codes in [-127, 127], one scale per output
channel (the largest |weight| of the channel is code 127). The Cast and the Mul read
initializers only, so ONNX Runtime's constant folding turns them back into one float weight
when the session is built: the file is the 8-bit codes, the step is an fp32 step. (OpenVINO
keeps such a weight compressed and decompresses it in its kernels at every step: float all the
same, a little slower.) A weight that another kind of node also reads stays float.

Why not a DequantizeLinear, which says the same more compactly: ONNX Runtime keeps one in
front of a MatMul and fuses the pair into MatMulNBits, which by default quantises the
activations on the fly (`session.qdq_matmulnbits_accuracy_level` 4): an 8-bit rounding of
activations, ISA by ISA, which is what this mode exists to avoid, and a session option every
application would have to set to avoid it.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import onnx
from onnx import helper, numpy_helper

from e3dpsm.onnx_graph import drop_unused_initializers

MODE = "int8-weights"  # the graph's quantisation mode (its metadata), and the artifact's precision
WEIGHTED_OPS = ("Conv", "Gemm", "MatMul")


def channel_shape(ndim: int, axis: int) -> list[int]:
    """The shape a per-channel vector along `axis` broadcasts against a tensor of `ndim` axes in."""
    shape = [1] * ndim
    shape[axis] = -1
    return shape


def output_channel_axis(node: onnx.NodeProto, weight: np.ndarray) -> int | None:
    """The axis of `weight` (the node's second input) that indexes its output channels: Conv's
    0 ([out, in, kh, kw]), Gemm's 0 with transB else 1, MatMul's last ([..., K, N]); None for
    a weight that is not a matrix or kernel."""
    if weight.ndim < 2:
        return None
    if node.op_type == "Conv":
        return 0
    if node.op_type == "Gemm":
        trans_b = next((a.i for a in node.attribute if a.name == "transB"), 0)
        return 0 if trans_b else 1
    return weight.ndim - 1


def symmetric_codes(weight: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """(int8 codes, float32 scales) with weight ~= codes * scale along `axis`; a channel of zeros
    gets scale 1 (its codes are 0 either way)."""
    others = tuple(d for d in range(weight.ndim) if d != axis)
    scale = np.abs(weight).max(axis=others).astype(np.float32) / np.float32(127.0)
    scale[scale == 0] = 1.0
    codes = np.clip(np.rint(weight / scale.reshape(channel_shape(weight.ndim, axis))), -127, 127).astype(np.int8)
    return codes, scale


def weight_only_int8(source: onnx.ModelProto) -> tuple[onnx.ModelProto, dict[str, Any]]:
    """(a copy of `source` with its weights in 8 bits as the module doc says, what was done)."""
    model = onnx.ModelProto()
    model.CopyFrom(source)
    graph = model.graph
    initializers = {i.name: i for i in graph.initializer}
    # A weight read anywhere but as a Conv / Gemm / MatMul's second input (an Add of the same
    # constant, a subgraph) stays float: its rebuild would not shrink the file.
    other_readers = {i for n in graph.node for k, i in enumerate(n.input) if k != 1 or n.op_type not in WEIGHTED_OPS}
    other_readers |= {i for n in graph.node for a in n.attribute if a.type == onnx.AttributeProto.GRAPH
                      for sub in a.g.node for i in sub.input}
    rebuilt: dict[str, str] = {}  # weight name -> its float rebuild's output (a weight shared by nodes: once)
    front: list[onnx.NodeProto] = []
    float_bytes = stored_bytes = 0
    for node in graph.node:
        if node.op_type not in WEIGHTED_OPS or len(node.input) < 2 or node.input[1] not in initializers \
                or node.input[1] in other_readers:
            continue
        name = node.input[1]
        if name not in rebuilt:
            weight = numpy_helper.to_array(initializers[name])
            axis = output_channel_axis(node, weight)
            if axis is None or weight.dtype != np.float32:
                continue
            codes, scale = symmetric_codes(weight, axis)
            graph.initializer.extend([numpy_helper.from_array(codes, f"{name}__int8"),
                                      numpy_helper.from_array(scale.reshape(channel_shape(weight.ndim, axis)),
                                                              f"{name}__scale")])
            front += [helper.make_node("Cast", [f"{name}__int8"], [f"{name}__codes"], to=onnx.TensorProto.FLOAT,
                                       name=f"{name}__cast"),
                      helper.make_node("Mul", [f"{name}__codes", f"{name}__scale"], [f"{name}__dequantized"],
                                       name=f"{name}__dequantize")]
            rebuilt[name] = f"{name}__dequantized"
            float_bytes += weight.nbytes
            stored_bytes += codes.nbytes + scale.nbytes
        node.input[1] = rebuilt[name]
    nodes = front + list(graph.node)  # the rebuilds read initializers only: first keeps the order topological
    del graph.node[:]
    graph.node.extend(nodes)
    drop_unused_initializers(model, among=rebuilt)
    return model, {"weights_int8": len(rebuilt), "weight_bytes_float": float_bytes,
                   "weight_bytes_stored": stored_bytes, "arithmetic": "float",
                   "scheme": "symmetric int8 per output channel, Cast and Mul folded at load"}


__all__ = ["MODE", "WEIGHTED_OPS", "channel_shape", "output_channel_axis", "symmetric_codes", "weight_only_int8"]
