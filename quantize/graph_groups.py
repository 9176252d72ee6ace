"""Groups of an exported step graph for the quantiser.

- Recurrent groups (always kept in float under INT8, and in float32 under FP16):
  `e3dpsm.onnx_groups.recurrent_groups`, derived from the data flow of the states.
- Candidate groups for the automatic exclusion search: per module scope (`stem`,
  `stages.2`, `attention.0`, `ssm`, `decoder`, ...; `e3dpsm.onnx_groups.module_scopes`)
  and per op type (`op:LayerNormalization`, `op:Softmax`, ...).
"""
from __future__ import annotations

from collections import defaultdict
from typing import Iterable

import onnx

from e3dpsm.onnx_groups import OTHER, NodeGroup, module_scopes, recurrent_groups, require_named_nodes

__all__ = ["NodeGroup", "OP_TYPE_CANDIDATES", "QUANTISABLE", "candidate_groups", "isolate_state_reads",
           "recurrent_groups"]

# Ops the INT8 quantiser would touch: only these make a candidate group worth trying.
QUANTISABLE = frozenset({"Conv", "MatMul", "Gemm", "Add", "Mul", "Sigmoid", "Softmax",
                         "LayerNormalization", "InstanceNormalization", "Relu", "Transpose",
                         "Reshape", "Concat", "GridSample", "ReduceSum", "Sub", "Div", "Erf"})
OP_TYPE_CANDIDATES = ("LayerNormalization", "Softmax", "InstanceNormalization", "Sigmoid", "Add", "Mul")


def candidate_groups(model: onnx.ModelProto, keep_float: Iterable[str] = ()) -> list[NodeGroup]:
    """Groups the exclusion search may add: module scopes, then op types; nodes already kept
    in float are left out, and groups without a quantisable op are dropped."""
    require_named_nodes(model)
    kept = set(keep_float)
    by_scope: dict[str, list[str]] = defaultdict(list)
    for name, scope in module_scopes(model).items():
        if scope != OTHER and name not in kept:
            by_scope[scope].append(name)
    by_op: dict[str, list[str]] = defaultdict(list)
    for node in model.graph.node:
        if node.op_type in OP_TYPE_CANDIDATES and node.name not in kept:
            by_op[node.op_type].append(node.name)
    op_of = {n.name: n.op_type for n in model.graph.node}
    groups = [NodeGroup(s, "module", tuple(v)) for s, v in by_scope.items()]
    groups += [NodeGroup(f"op:{op}", "op_type", tuple(by_op[op])) for op in OP_TYPE_CANDIDATES if by_op.get(op)]
    return [g for g in groups if any(op_of[n] in QUANTISABLE for n in g.nodes)]


STATE_READ_SUFFIX = "/state_read"


def isolate_state_reads(model: onnx.ModelProto, nodes: Iterable[str]) -> list[str]:
    """Give each of `nodes` that reads a graph output (a recurrent state an S5 readout reads
    in the step that writes it) its own copy of that tensor, through an Identity, in place;
    returns the names of the nodes rewired.

    Why: ONNX Runtime's quantiser puts a quantised tensor's Q/DQ pair on the tensor itself;
    on a graph output it then outputs the rounded value, and the state carried to the next
    step would be rounded. On the copy only the reading node sees it. The fp32 function is
    unchanged, and ONNX Runtime's optimiser removes the Identity when it loads the graph."""
    outputs = {o.name for o in model.graph.output}
    wanted = set(nodes)
    rewired: list[str] = []
    index = 0
    while index < len(model.graph.node):
        node = model.graph.node[index]
        reads = [t for t in node.input if t in outputs] if node.name in wanted else []
        for tensor in dict.fromkeys(reads):
            copy = f"{node.name}/{tensor}{STATE_READ_SUFFIX}"
            model.graph.node.insert(index, onnx.helper.make_node("Identity", [tensor], [copy],
                                                                name=f"{node.name}{STATE_READ_SUFFIX}"))
            index += 1
            for i, name in enumerate(node.input):
                if name == tensor:
                    node.input[i] = copy
        if reads:
            rewired.append(node.name)
        index += 1
    return rewired
