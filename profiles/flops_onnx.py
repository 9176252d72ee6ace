"""Count one pose update on an exported step graph, per module group (convention: profiles.flops).

Shapes: the batch axis is fixed at 1 and `onnx.shape_inference` runs with data propagation;
tensors it leaves symbolic (the decoder's Expand of the queries) are measured from one
onnxruntime run at batch 1. Modules: node names carry the PyTorch module scope
(`/stages.0/block1/conv1/Conv`), or onnxsim keeps it in an output name; see
profiles.graph_groups for the nodes that carry none.
"""
from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, numpy_helper

from e3dpsm.errors import DataError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.onnx_graph import node_key
from e3dpsm.profiles.flops import FlopCount, grid_sample_macs, recurrence_macs
from e3dpsm.profiles.graph_groups import assign_groups

DENSE_OPS = ("Conv", "Gemm", "MatMul")
SAMPLING_OPS = ("GridSample", "DeformConv")
# Nodes that do arithmetic on every output value (reported as "elementwise", not in MACs).
ELEMENTWISE_OPS = frozenset({
    "Add", "Sub", "Mul", "Div", "Pow", "Sqrt", "Exp", "Log", "Erf", "Tanh", "Sigmoid", "Relu",
    "LeakyRelu", "Neg", "Abs", "Reciprocal", "Clip", "Max", "Min", "Softmax", "LayerNormalization",
    "BatchNormalization", "InstanceNormalization", "GroupNormalization", "ReduceSum", "ReduceMean",
    "Gelu", "Where", "Cos", "Sin",
})
Shapes = dict[str, tuple[int, ...]]


def load_graph(path: str | os.PathLike) -> onnx.ModelProto:
    try:
        return onnx.load(str(path))
    except FileNotFoundError:
        raise DataError(f"model {path} does not exist") from None
    except Exception as exc:  # protobuf decode errors have no common public type
        raise DataError(f"{path} is not a readable ONNX file: {str(exc).splitlines()[0][:200]}") from exc


def _fix_batch(model: onnx.ModelProto) -> onnx.ModelProto:
    fixed = onnx.ModelProto()
    fixed.CopyFrom(model)
    for value in [*fixed.graph.input, *fixed.graph.output]:
        dims = value.type.tensor_type.shape.dim
        if dims and not dims[0].HasField("dim_value"):
            dims[0].dim_value = 1
    return fixed


def _known(value: onnx.ValueInfoProto) -> tuple[int, ...] | None:
    tensor = value.type.tensor_type
    if not tensor.HasField("shape") or any(not d.HasField("dim_value") for d in tensor.shape.dim):
        return None
    return tuple(int(d.dim_value) for d in tensor.shape.dim)


def static_shapes(model: onnx.ModelProto) -> tuple[Shapes, dict[str, int]]:
    """Shapes and element types of every tensor of the graph at batch 1."""
    inferred = onnx.shape_inference.infer_shapes(_fix_batch(model), data_prop=True)
    shapes: Shapes = {}
    dtypes: dict[str, int] = {}
    for init in inferred.graph.initializer:
        shapes[init.name], dtypes[init.name] = tuple(init.dims), init.data_type
    for value in [*inferred.graph.input, *inferred.graph.output, *inferred.graph.value_info]:
        dtypes[value.name] = value.type.tensor_type.elem_type
        shape = _known(value)
        if shape is not None:
            shapes[value.name] = shape
    wanted = {t for n in inferred.graph.node if n.op_type in (*DENSE_OPS, *SAMPLING_OPS) for t in (*n.input, *n.output)}
    missing = sorted(t for t in wanted if t and t not in shapes)
    if missing:
        shapes.update(_measured_shapes(inferred, missing, dtypes))
    return shapes, dtypes


def _measured_shapes(model: onnx.ModelProto, names: list[str], dtypes: dict[str, int]) -> Shapes:
    """Shapes of `names` from one onnxruntime run at batch 1 with the graph's initial state."""
    import onnxruntime as ort

    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    known_outputs = {o.name for o in probe.graph.output}
    for name in names:
        if name not in known_outputs:
            probe.graph.output.append(onnx.helper.make_value_info(
                name, onnx.helper.make_tensor_type_proto(dtypes.get(name) or TensorProto.FLOAT, None)))
    meta = GraphMetadata.from_onnx(model)
    feeds: dict[str, np.ndarray] = {meta.frame_input["name"]: np.zeros((1, *meta.frame_input["shape"][1:]), np.float32),
                                    meta.window_input["name"]: np.full((1,), meta.train_window_ms, np.float32)}
    feeds.update({s.input_name: s.initial_value(1) for s in meta.states})
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL  # keep every tensor
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(probe.SerializeToString(), options, providers=["CPUExecutionProvider"])
    values = session.run(names, feeds)
    return {name: tuple(value.shape) for name, value in zip(names, values)}


def _dense_macs(node: onnx.NodeProto, shapes: Shapes) -> int:
    out = shapes[node.output[0]]
    if node.op_type in ("Conv", "DeformConv"):
        weight = shapes[node.input[1]]
        return math.prod(out) * math.prod(weight[1:])  # weight [Cout, Cin/groups, kh, kw]
    if node.op_type == "Gemm":
        a = shapes[node.input[0]]
        trans_a = next((attr.i for attr in node.attribute if attr.name == "transA"), 0)
        return math.prod(out) * (a[0] if trans_a else a[1])
    a = shapes[node.input[0]]  # MatMul, numpy semantics: out [..., M, N], K = a[-1]
    return math.prod(out) * a[-1]


def count_onnx(model: onnx.ModelProto | str | os.PathLike) -> FlopCount:
    """Per-module MACs of one step of an exported graph (fp32 graphs; QDQ graphs count the
    float ops that remain). Raises MetadataError for a graph without e3dpsm metadata."""
    if not isinstance(model, onnx.ModelProto):
        model = load_graph(model)
    meta = GraphMetadata.from_onnx(model)
    shapes, dtypes = static_shapes(model)
    groups = assign_groups(model, dtypes)
    result = FlopCount("onnx", notes=[
        "Conv / Gemm / MatMul MACs from shapes at batch 1; GridSample, DeformConv sampling, S5 and Kalman by "
        "formula (a DeformConv adds its kernel's MACs as dense); "
        "'elementwise' = output values of other arithmetic nodes (not in MACs)"])
    for module in result.modules.values():
        module.elementwise = 0
    for node in model.graph.node:
        group = groups[node_key(node)]
        if node.op_type in DENSE_OPS:
            result.add(group, "dense", _dense_macs(node, shapes))
        elif node.op_type == "GridSample":
            n, c = shapes[node.input[0]][:2]
            out_h, out_w = shapes[node.output[0]][2:]
            result.add(group, "sampling", grid_sample_macs(n, c, out_h, out_w))
        elif node.op_type == "DeformConv":
            # Every input channel is sampled at each kernel tap of each output position.
            n, c = shapes[node.input[0]][:2]
            out_h, out_w = shapes[node.output[0]][2:]
            taps = math.prod(shapes[node.input[1]][2:])
            result.add(group, "sampling", grid_sample_macs(n, c, out_h, out_w * taps))
            result.add(group, "dense", _dense_macs(node, shapes))
        elif node.op_type in ELEMENTWISE_OPS and node.output[0] in shapes:
            result.add(group, "elementwise", math.prod(shapes[node.output[0]]))
    for group, macs in recurrence_macs(meta.states, meta.config.get("model_config", {"widths": []})).items():
        result.add(group, "recurrence", macs)
    return result


def initializer_values(model: onnx.ModelProto) -> int:
    """Stored numbers in the graph (parameters after constant folding; shared constants once)."""
    return sum(math.prod(init.dims) for init in model.graph.initializer)


def activation_bytes(model: onnx.ModelProto) -> int:
    """Bytes of every intermediate tensor of one step at batch 1 (each written once)."""
    shapes, dtypes = static_shapes(model)
    params = {init.name for init in model.graph.initializer}
    total = 0
    for node in model.graph.node:
        for name in node.output:
            if name in shapes and name not in params and node.op_type not in ("Constant", "Shape"):
                itemsize = np.dtype(onnx.helper.tensor_dtype_to_np_dtype(dtypes.get(name, TensorProto.FLOAT))).itemsize
                total += math.prod(shapes[name]) * itemsize
    return total


def weight_bytes(model: onnx.ModelProto) -> int:
    return sum(numpy_helper.to_array(init).nbytes if not init.raw_data else len(init.raw_data)
               for init in model.graph.initializer)


def graph_summary(model: onnx.ModelProto) -> dict[str, Any]:
    return {"nodes": len(model.graph.node), "initializer_values": initializer_values(model),
            "weight_bytes": weight_bytes(model), "activation_bytes": activation_bytes(model)}
