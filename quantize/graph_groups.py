"""Node groups of an exported step graph, found from its structure and metadata.

Two kinds of groups:

- Recurrent groups (always kept in float under INT8, and in float32 under FP16): one per
  family of state tensors (`s5_stage1_re/_im` -> `s5_stage1`, `fusion_pose/_cov/...` ->
  `fusion`). Node names cannot find them: the legacy exporter leaves the functional S5
  step unscoped (`/Mul_12`) and onnxsim renames fused Gemms (`Gemm_69`). So a group is
  derived from the data flow instead:
    core     nodes on a path from one of the family's state inputs to one of its outputs
             (the state update: S5 `x' = A x + B u`, Kalman predict/update, pose embedding);
    inject   producers feeding the core through elementwise ops, up to and including the
             first MatMul/Gemm (S5 `B u`, the direct pose head that Kalman consumes);
    params   producers that do not depend on the frame or any state (the discretisation
             of Lambda and B from `window_ms`, exp(log Q), exp(log R));
    readout  consumers of the core through elementwise/shape ops, plus a MatMul that reads
             the state directly (S5 `Re(C x) + D u`, GELU and the residual add), stopping
             at normalisations, convolutions and other MatMuls.
- Candidate groups for the automatic exclusion search: per module scope (`stem`,
  `stages.2`, `attention.0`, `decoder`, ...; unscoped nodes inherit a neighbour's scope)
  and per op type (`op:LayerNormalization`, `op:Softmax`, ...).
"""
from __future__ import annotations

import re
from collections import defaultdict
from dataclasses import dataclass
from typing import Iterable

import onnx

from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.onnx_graph import GraphIndex

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
# Ops the INT8 quantiser would touch: only these make a candidate group worth trying.
QUANTISABLE = frozenset({"Conv", "MatMul", "Gemm", "Add", "Mul", "Sigmoid", "Softmax",
                         "LayerNormalization", "InstanceNormalization", "Relu", "Transpose",
                         "Reshape", "Concat", "GridSample", "ReduceSum", "Sub", "Div", "Erf"})
# Module scopes of the E-3DPSM graph, as the legacy exporter writes them (`/stages.0/...`).
MODULE_SCOPE = re.compile(r"^(stem|stages\.\d+|attention\.\d+|decoder|direct_head|pose_embed|delta_head|fusion)$")
OP_TYPE_CANDIDATES = ("LayerNormalization", "Softmax", "InstanceNormalization", "Sigmoid", "Add", "Mul")


@dataclass(frozen=True)
class NodeGroup:
    """A named set of node names, with why it exists (`kind`: recurrent, module, op_type)."""

    name: str
    kind: str
    nodes: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.nodes)


def _named_index(model: onnx.ModelProto) -> GraphIndex:
    # The quantiser keeps nodes in float by name, so every node needs one.
    if any(not node.name for node in model.graph.node):
        raise ValueError("graph has unnamed nodes; re-export it")
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


def module_scopes(model: onnx.ModelProto) -> dict[str, str]:
    """Node name -> module scope ("" if none).

    Nodes onnxsim renamed (no leading "/": `Gemm_3`) take the scope of their output
    tensor's name, else of a non-constant neighbour. Top-level exporter names (`/Mul_12`,
    the functional S5 step) stay unscoped: they belong to no module.
    """
    index = _named_index(model)

    def scope_of(text: str) -> str:
        head = text.split("/")[1] if text.startswith("/") and text.count("/") >= 2 else ""
        return head if MODULE_SCOPE.match(head) else ""

    scopes = {}
    for name, node in index.nodes.items():
        scopes[name] = scope_of(name) or next((s for s in map(scope_of, node.output) if s), "")
    renamed = [n for n in index.nodes if not n.startswith("/") and not scopes[n]]
    for _ in range(8):  # a few sweeps settle chains of renamed nodes
        changed = False
        for name in renamed:
            if scopes[name]:
                continue
            neighbours = [n for n in index.consumers_of(name) + index.producers_of(name)
                          if index.nodes[n].op_type != "Constant"]
            found = next((scopes[n] for n in neighbours if scopes[n]), "")
            if found:
                scopes[name], changed = found, True
        if not changed:
            break
    return scopes


def candidate_groups(model: onnx.ModelProto, keep_float: Iterable[str] = ()) -> list[NodeGroup]:
    """Groups the exclusion search may add: module scopes, then op types; nodes already kept
    in float are left out, and groups without a quantisable op are dropped."""
    kept = set(keep_float)
    by_scope: dict[str, list[str]] = defaultdict(list)
    for name, scope in module_scopes(model).items():
        if scope and name not in kept:
            by_scope[scope].append(name)
    by_op: dict[str, list[str]] = defaultdict(list)
    for node in model.graph.node:
        if node.op_type in OP_TYPE_CANDIDATES and node.name not in kept:
            by_op[node.op_type].append(node.name)
    op_of = {n.name: n.op_type for n in model.graph.node}
    groups = [NodeGroup(s, "module", tuple(v)) for s, v in by_scope.items()]
    groups += [NodeGroup(f"op:{op}", "op_type", tuple(by_op[op])) for op in OP_TYPE_CANDIDATES if by_op.get(op)]
    return [g for g in groups if any(op_of[n] in QUANTISABLE for n in g.nodes)]
