"""FP16 conversion with float32 inputs/outputs (callers keep feeding float32 frames and
states), the recurrent parts kept in float32 (a state carried over thousands of steps in
fp16 accumulates rounding), and ops ORT's CPU provider has no fp16 kernel for left in
float32 (onnxconverter-common inserts the Casts around them)."""
from __future__ import annotations

import copy
from collections import defaultdict
from typing import Callable, Iterable

import onnx

# onnxconverter-common's own default block list, plus ops seen in the E-3DPSM graph that
# ORT 1.31 CPU cannot run in fp16 or runs inaccurately: GridSample and DeformConv (no fp16
# CPU kernels; deformable sampling offsets need float32 anyway), InstanceNormalization / LayerNormalization
# (mean/variance over many values), Erf (GELU), Pow/Exp (discretisation, Kalman gains), Tile
# (no fp16 CPU kernel: ORT could not fold the export's tiled constants, onnx_constants.py, on
# load, and ran them every step behind casts; in float32 they fold, the cast after them too).
FP16_OP_BLOCK_LIST: tuple[str, ...] = (
    "GridSample", "DeformConv", "InstanceNormalization", "LayerNormalization", "Erf", "Pow", "Exp", "Softmax",
    "Resize", "Range", "ConstantOfShape", "Where", "Tile",
)


def isolate_outputs(model: onnx.ModelProto) -> list[str]:
    """Make every graph output the output of its own Identity node; return their names.

    The step graph reads some of its outputs back inside (the new S5 state feeds the
    readout, the fused pose feeds `fusion_pose_out`). onnxconverter-common's keep_io_types
    then casts such an output to fp16 for the internal readers even when they are blocked
    in float32, and ORT refuses the mixed-type MatMul. With the Identity split, internal
    readers see an ordinary tensor and the outputs a float32 Identity.
    """
    outputs = {o.name for o in model.graph.output}
    added = []
    for node in list(model.graph.node):
        for k, name in enumerate(node.output):
            if name in outputs:
                inner = f"{name}__internal"
                node.output[k] = inner
                for other in model.graph.node:
                    for j, inp in enumerate(other.input):
                        if inp == name:
                            other.input[j] = inner
                ident = onnx.helper.make_node("Identity", [inner], [name], name=f"{name}__identity")
                model.graph.node.append(ident)
                added.append(ident.name)
    return added


def unshare_initializers(model: onnx.ModelProto, stays_float: Callable[[onnx.NodeProto], bool]) -> None:
    """Give the float32-kept readers of an initializer their own copy when fp16 nodes read it too.

    onnxsim merges identical initializers (zero-initialised attention weights of two blocks
    become one tensor); the converter then casts the shared tensor for one reader and the
    other reader meets the wrong type ("MatMul bound to different types").
    """
    initializers = {i.name: i for i in model.graph.initializer}
    readers: dict[str, list[tuple[onnx.NodeProto, int]]] = defaultdict(list)
    for node in model.graph.node:
        for k, name in enumerate(node.input):
            if name in initializers:
                readers[name].append((node, k))
    for name, uses in readers.items():
        kept = [(node, k) for node, k in uses if stays_float(node)]
        if kept and len(kept) < len(uses):
            twin = onnx.TensorProto()
            twin.CopyFrom(initializers[name])
            twin.name = f"{name}__float32"
            model.graph.initializer.append(twin)
            for node, k in kept:
                node.input[k] = twin.name


def convert_fp16(model: onnx.ModelProto, keep_float: Iterable[str] = ()) -> onnx.ModelProto:
    """An fp16 copy of `model` (float32 I/O; `keep_float` nodes and blocked ops in float32)."""
    from onnxconverter_common import float16

    keep_float = set(keep_float)
    model = copy.deepcopy(model)
    identities = isolate_outputs(model)
    block = sorted(set(float16.DEFAULT_OP_BLOCK_LIST) | set(FP16_OP_BLOCK_LIST))
    unshare_initializers(model, lambda node: node.name in keep_float or node.op_type in block)
    converted = float16.convert_float_to_float16(
        model, keep_io_types=True, disable_shape_infer=False, op_block_list=block,
        node_block_list=sorted(keep_float | set(identities)),
    )
    _drop_round_trips(converted)
    _float_outputs(converted)
    return converted


def _cast_to(node: onnx.NodeProto) -> int | None:
    return next((a.i for a in node.attribute if a.name == "to"), None) if node.op_type == "Cast" else None


def _drop_round_trips(model: onnx.ModelProto) -> None:
    """Remove Cast(fp16) -> Cast(fp32) pairs the converter puts between adjacent blocked
    nodes: they would round the carried pose (0.5 mm steps at 1 m) and the S5 states."""
    f16, f32 = onnx.TensorProto.FLOAT16, onnx.TensorProto.FLOAT
    graph = model.graph
    outputs = {o.name for o in graph.output}
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in graph.node:
        for inp in node.input:
            consumers.setdefault(inp, []).append(node)
    drop = set()
    for node in graph.node:
        readers = consumers.get(node.output[0], []) if _cast_to(node) == f16 else []
        if not readers or node.output[0] in outputs or any(_cast_to(r) != f32 for r in readers):
            continue
        source = node.input[0]
        for reader in readers:
            if reader.output[0] in outputs:  # keep the output name: the reader becomes an Identity
                reader.op_type, reader.input[0] = "Identity", source
                del reader.attribute[:]
                continue
            for other in consumers.get(reader.output[0], []):
                for j, inp in enumerate(other.input):
                    if inp == reader.output[0]:
                        other.input[j] = source
            drop.add(id(reader))
        drop.add(id(node))
    kept = [n for n in graph.node if id(n) not in drop]
    del graph.node[:]
    graph.node.extend(kept)


def _float_outputs(model: onnx.ModelProto) -> None:
    """Graph outputs the converter left in fp16 get a final Cast to float32."""
    graph = model.graph
    for out in graph.output:
        if out.type.tensor_type.elem_type != onnx.TensorProto.FLOAT16:
            continue
        out.type.tensor_type.elem_type = onnx.TensorProto.FLOAT
        producer = next(n for n in graph.node if out.name in n.output)
        if _cast_to(producer) == onnx.TensorProto.FLOAT16:
            # The converter's last cast: cast to float32 instead (no fp16 rounding of outputs
            # computed in float32, e.g. the fused pose and the states).
            next(a for a in producer.attribute if a.name == "to").i = onnx.TensorProto.FLOAT
            continue
        inner = f"{out.name}__fp16"
        for node in graph.node:
            for k, name in enumerate(node.output):
                if name == out.name:
                    node.output[k] = inner
        graph.node.append(onnx.helper.make_node("Cast", [inner], [out.name], name=f"{out.name}__to_fp32",
                                                to=onnx.TensorProto.FLOAT))
