"""Node groups of an exported step graph: which module each node belongs to, and which
nodes carry the recurrent state. Needs onnx only (no torch): diagnose runs on edge devices.

Module scopes (`module_scopes`), one algorithm for every consumer: the quantiser's
candidate groups (`stages.2`, `attention.0`, ...), the profiler's per-module figures (which
map these scopes onto the paper's coarser groups) and diagnose's groups.

1. Scope: the legacy tracer names nodes after the PyTorch module path (`/stages.0/block1/
   conv1/Conv`, `/decoder/layers.0/...`); the first path component that is a top-level
   module of the model is the node's scope. onnxsim's fused nodes (`Gemm_27`) often keep
   it in their output's name (`/delta_head/Add_output_0`).
2. S5 anchors: the model calls its S5 blocks through `block.step(...)`, which the tracer
   does not scope, so their nodes carry bare names (`/Mul_3`, `/norm1/...`). Nodes reading
   or writing an `s5_*` state are S5 work (`ssm`), and so is every unscoped node connected
   to them by activation tensors.
3. The remaining unscoped nodes take the scope their labelled producers agree on, else the
   one their consumers agree on (repeated until nothing changes); leftovers are OTHER.

Labels travel along activation tensors only (float, and 8-bit for the quantised tensors
of QDQ graphs): int64 / int32 tensors are shape arithmetic, shared across modules, so a
`Shape -> Slice -> Concat` chain belongs to no module.

Recurrent groups (`recurrent_groups`; the quantiser keeps them in float, diagnose reports
them first): one per family of state tensors (`s5_stage1_re/_im` -> `s5_stage1`,
`fusion_pose/_cov/...` -> `fusion`). Node names cannot find them: the legacy exporter leaves
the functional S5 step unscoped (`/Mul_12`) and onnxsim renames fused Gemms (`Gemm_69`). So
a group is derived from the data flow instead:
    core     nodes on a path from one of the family's state inputs to one of its outputs
             (the state update: S5 `x' = A x + B u`, Kalman predict/update, pose embedding);
    inject   producers feeding the core through elementwise ops, up to and including the
             first MatMul/Gemm (S5 `B u`, the direct pose head that Kalman consumes);
    params   producers that do not depend on the frame or any state (the discretisation
             of Lambda and B from `window_ms`, exp(log Q), exp(log R));
    readout  consumers of the core through elementwise/shape ops, plus a MatMul that reads
             the state directly (S5 `Re(C x) + D u`, GELU and the residual add), stopping
             at normalisations, convolutions and other MatMuls.
"""
from __future__ import annotations

import re
from collections import defaultdict
from dataclasses import dataclass
from typing import Mapping

import onnx
from onnx import TensorProto

from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.onnx_graph import GraphIndex

OTHER = "other"
SSM = "ssm"
# Top-level modules of the E3DPSM model as the legacy exporter writes them (`/stages.0/...`).
MODULE_SCOPE = re.compile(r"^(stem|stages\.\d+|attention\.\d+|ssm(\.\w+)?|decoder|direct_head|pose_embed|delta_head"
                          r"|fusion)$")
ACTIVATION_TYPES = frozenset({TensorProto.FLOAT, TensorProto.FLOAT16, TensorProto.DOUBLE, TensorProto.BFLOAT16,
                              TensorProto.UINT8, TensorProto.INT8})
_SSM_STATE_PREFIX = "s5_"
ELEMENTWISE = frozenset({
    "Add", "Sub", "Mul", "Div", "Pow", "Neg", "Exp", "Log", "Sqrt", "Reciprocal", "Abs", "Erf",
    "Sigmoid", "Tanh", "Relu", "Where", "Equal", "Less", "Greater", "Not", "And", "Or", "Clip",
    "Min", "Max",
})
SHAPE_OPS = frozenset({
    "Reshape", "Transpose", "Unsqueeze", "Squeeze", "Concat", "Slice", "Gather", "Expand",
    "Identity", "Shape", "ConstantOfShape", "Flatten", "Cast", "Split", "Constant",
})
PROJECTIONS = frozenset({"MatMul", "Gemm"})


@dataclass(frozen=True)
class NodeGroup:
    """A named set of node names, with why it exists (`kind`: recurrent, module, op_type)."""

    name: str
    kind: str
    nodes: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.nodes)


def scope_of(name: str) -> str | None:
    """The module scope in a node or tensor name (`/stages.0/block1/Conv` -> `stages.0`), if any."""
    if not name.startswith("/"):
        return None
    for component in name[1:].split("/")[:-1]:  # the last component is the op or tensor name
        if MODULE_SCOPE.match(component):
            return component
    return None


def tensor_types(model: onnx.ModelProto) -> dict[str, int]:
    """Element type of every tensor shape inference can tell (initialisers included)."""
    inferred = onnx.shape_inference.infer_shapes(model)
    types = {init.name: init.data_type for init in inferred.graph.initializer}
    for value in (*inferred.graph.input, *inferred.graph.output, *inferred.graph.value_info):
        types[value.name] = value.type.tensor_type.elem_type
    return types


def module_scopes(model: onnx.ModelProto, dtypes: Mapping[str, int] | None = None) -> dict[str, str]:
    """node key (e3dpsm.onnx_graph.node_key) -> module scope, OTHER for none (module doc).

    `dtypes`: tensor element types (`tensor_types(model)` when not given); a tensor of
    unknown type counts as an activation.
    """
    types = tensor_types(model) if dtypes is None else dtypes
    index = GraphIndex(model)

    def is_activation(tensor: str) -> bool:
        return types.get(tensor, TensorProto.FLOAT) in ACTIVATION_TYPES

    labels: dict[str, str | None] = {
        key: next((s for s in map(scope_of, [node.name, *node.output]) if s), None)
        for key, node in index.nodes.items()}

    queue = [key for key, node in index.nodes.items() if labels[key] is None and any(
        t.startswith(_SSM_STATE_PREFIX) for t in (*node.input, *node.output))]
    for key in queue:
        labels[key] = SSM
    while queue:
        key = queue.pop()
        for other in index.producers_of(key, is_activation) + index.consumers_of(key, is_activation):
            if labels[other] is None and index.nodes[other].op_type != "Constant":
                labels[other] = SSM
                queue.append(other)

    changed = True
    while changed:
        changed = False
        for key in index.nodes:
            if labels[key] is not None:
                continue
            for side in (index.producers_of(key, is_activation), index.consumers_of(key, is_activation)):
                found = {labels[k] for k in side if labels[k] is not None}
                if len(found) == 1:
                    labels[key] = found.pop()
                    changed = True
                    break
    return {key: label or OTHER for key, label in labels.items()}


def require_named_nodes(model: onnx.ModelProto) -> None:
    """The quantiser keeps nodes in float by name, so every node needs one."""
    if any(not node.name for node in model.graph.node):
        raise ValueError("graph has unnamed nodes; re-export it")


def _named_index(model: onnx.ModelProto) -> GraphIndex:
    require_named_nodes(model)
    return GraphIndex(model)


def state_families(meta: GraphMetadata) -> dict[str, list]:
    """State specs grouped by family: the name without its last `_part` (`s5_stage1_re`)."""
    families: dict[str, list] = defaultdict(list)
    for spec in meta.states:
        family = spec.name.split("_")[0] if spec.name.startswith("fusion") else spec.name.rsplit("_", 1)[0]
        families[family].append(spec)
    return dict(families)


def _backward(index: GraphIndex, start: set[str], allowed) -> set[str]:
    found: set[str] = set()
    stack = [p for n in start for p in index.producers_of(n)]
    while stack:
        name = stack.pop()
        if name in found or name in start or not allowed(name):
            continue
        found.add(name)
        stack.extend(index.producers_of(name))
    return found


def recurrent_groups(model: onnx.ModelProto, meta: GraphMetadata | None = None) -> list[NodeGroup]:
    """The state-carrying parts of the graph, one group per state family (module doc)."""
    meta = meta or GraphMetadata.from_onnx(model)
    index = _named_index(model)
    frame_dependent = index.descendants([meta.frame_input["name"]])
    state_dependent = index.descendants(s.input_name for s in meta.states)
    groups = []
    for family, specs in state_families(meta).items():
        ins = [s.input_name for s in specs]
        outs = [s.output_name for s in specs]
        core = index.descendants(ins) & index.ancestors(outs)
        core |= {c for t in ins for c in index.consumers.get(t, [])}
        ops = lambda n: index.nodes[n].op_type  # noqa: E731

        inject: set[str] = set()
        frontier = [p for n in core for p in index.producers_of(n)]
        while frontier:
            name = frontier.pop()
            if name in core or name in inject or name not in frame_dependent:
                continue
            if ops(name) in ELEMENTWISE:
                inject.add(name)
                frontier.extend(index.producers_of(name))
            elif ops(name) in PROJECTIONS:
                inject.add(name)  # the projection into the recurrence; stop behind it

        members = core | inject
        members |= _backward(index, members, lambda n: n not in frame_dependent and n not in state_dependent)

        core_outputs = {o for n in core for o in index.nodes[n].output} | set(ins)
        readout: set[str] = set()
        stack = [c for n in core for c in index.consumers_of(n)] + [c for t in ins for c in index.consumers.get(t, [])]
        while stack:
            name = stack.pop()
            if name in members or name in readout:
                continue
            op = ops(name)
            reads_state = any(i in core_outputs for i in index.nodes[name].input)
            # Shape ops carry no values: following them would wander into unrelated modules.
            if op in ("Shape", "ConstantOfShape"):
                continue
            if op in ELEMENTWISE or op in SHAPE_OPS or (op in PROJECTIONS and reads_state):
                readout.add(name)
                stack.extend(index.consumers_of(name))
        members |= readout
        groups.append(NodeGroup(family, "recurrent", tuple(n for n in index.nodes if n in members)))
    return groups
