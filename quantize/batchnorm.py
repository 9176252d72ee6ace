"""Pre-activation BatchNorm as a per-channel 1x1 depthwise convolution, so INT8 can run it.

The CNN's blocks are pre-activation (`x -> BN -> SiLU -> Conv`, shortcut from the raw `x`):
no BatchNorm follows a convolution, so none folds into one exactly, and folding one into the
convolution before `x` would change what the shortcut sees. ONNX Runtime has no int8
BatchNorm, so in a QDQ graph each one runs in float between a DequantizeLinear and a
QuantizeLinear. In inference mode BatchNorm is the per-channel affine
`y = x * s + t` with `s = gamma / sqrt(var + eps)`, `t = beta - mean * s`, which is exactly
a grouped 1x1 Conv (group = channels, weight s, bias t); that Conv quantises per channel like
any other (QLinearConv), so the block's tensors can stay 8-bit end to end.
"""
from __future__ import annotations

import numpy as np
import onnx
from onnx import helper, numpy_helper

from e3dpsm.onnx_graph import drop_unused_initializers


def batchnorm_as_depthwise_conv(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """Copy of `model` with every inference-mode BatchNormalization on a 4-D input with
    constant parameters replaced by the equivalent depthwise 1x1 Conv (same node name and
    output tensor, so exclusion lists and calibration ranges stay valid); returns the model
    and how many were replaced."""
    model = onnx.ModelProto.FromString(model.SerializeToString())
    inits = {i.name: i for i in model.graph.initializer}
    ranks = _input_ranks(model)
    replaced = 0
    nodes = []
    for node in model.graph.node:
        params = node.input[1:5]
        if (node.op_type != "BatchNormalization" or len(node.output) != 1 or len(params) != 4
                or not all(p in inits for p in params) or ranks.get(node.input[0]) != 4):
            nodes.append(node)
            continue
        gamma, beta, mean, var = (numpy_helper.to_array(inits[p]).astype(np.float64) for p in params)
        eps = next((a.f for a in node.attribute if a.name == "epsilon"), 1e-5)
        scale = gamma / np.sqrt(var + eps)
        shift = beta - mean * scale
        channels = scale.shape[0]
        w_name, b_name = f"{node.name}/dw_weight", f"{node.name}/dw_bias"
        model.graph.initializer.extend([
            numpy_helper.from_array(scale.reshape(channels, 1, 1, 1).astype(np.float32), w_name),
            numpy_helper.from_array(shift.astype(np.float32), b_name)])
        nodes.append(helper.make_node("Conv", [node.input[0], w_name, b_name], list(node.output), name=node.name,
                                      group=channels, kernel_shape=[1, 1]))
        replaced += 1
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    drop_unused_initializers(model)
    return model, replaced


def _input_ranks(model: onnx.ModelProto) -> dict[str, int]:
    ranks = {}
    for vi in [*model.graph.value_info, *model.graph.input, *model.graph.output]:
        if vi.type.tensor_type.HasField("shape"):
            ranks[vi.name] = len(vi.type.tensor_type.shape.dim)
    return ranks
