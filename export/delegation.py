"""How much of a lowered ExecuTorch program runs in its backend: the multiply-accumulates of
the step inside delegate calls against those left on portable kernels, and which operators
stay outside (convert.json's `delegation`).

MACs are counted on the operators that carry nearly all of them: convolution (output values
x input channels per group x kernel area), linear / addmm / mm / bmm (output values x
reduced length) and grid sampling (4 per output value: the bilinear corners). Elementwise
ops, norms and copies count 0 here."""
from __future__ import annotations

import math
from collections import Counter
from typing import Any

import torch

DELEGATE_CALL = "executorch_call_delegate"
_NOT_COMPUTE = ("getitem", DELEGATE_CALL)


def _shape(value: Any) -> tuple[int, ...]:
    val = value.meta.get("val") if isinstance(value, torch.fx.Node) else None
    return tuple(int(d) for d in val.shape) if isinstance(val, torch.Tensor) else ()


def op_name(node: torch.fx.Node) -> str:
    """`aten.mm.default` for an edge or ATen operator node; other callables by their name
    (`getitem`, `executorch_call_delegate`)."""
    target = node.target
    wrapped = getattr(target, "_op", None)
    if isinstance(wrapped, torch._ops.OpOverload):  # an edge operator wraps its ATen one
        target = wrapped
    if isinstance(target, torch._ops.OpOverload):
        return str(target)
    return getattr(target, "__name__", None) or str(target)


def module_scope(node: torch.fx.Node) -> str:
    """The innermost module path of a traced node ("" when the trace kept none)."""
    stack = node.meta.get("nn_module_stack") or {}
    paths = [v[0] for v in stack.values()]
    return paths[-1] if paths else ""


def node_macs(node: torch.fx.Node) -> int:
    if node.op != "call_function":
        return 0
    name = op_name(node)
    out = _shape(node)
    outputs = math.prod(out) if out else 0
    if "convolution" in name:
        weight = _shape(node.args[1])
        return outputs * math.prod(weight[1:]) if weight else 0
    if name.startswith(("aten.linear", "aten.mm", "aten.bmm")) or name.startswith("aten.addmm"):
        reduced = _shape(node.args[1])[-1] if "linear" in name or "addmm" in name else _shape(node.args[0])[-1]
        return outputs * reduced
    if "grid_sampler" in name:
        return 4 * outputs
    return 0


def _compute_nodes(graph: torch.fx.Graph) -> list[torch.fx.Node]:
    return [n for n in graph.nodes if n.op == "call_function" and not any(k in op_name(n) for k in _NOT_COMPUTE)]


def delegation_summary(edge_manager: Any) -> dict[str, Any]:
    """{delegated_macs, portable_macs, delegated_share, delegates, portable_ops} of an
    `EdgeProgramManager` after `to_edge_transform_and_lower`."""
    program = edge_manager.exported_program()
    module = program.graph_module
    delegated = 0
    delegates = 0
    for name, child in module.named_children():
        original = getattr(child, "original_module", None)
        if original is not None:
            delegates += 1
            delegated += sum(node_macs(n) for n in original.graph.nodes)
    outside = _compute_nodes(program.graph)
    portable = sum(node_macs(n) for n in outside)
    ops = Counter(op_name(n) for n in outside)
    total = delegated + portable
    return {
        "delegated_macs": delegated, "portable_macs": portable,
        "delegated_share": delegated / total if total else None, "delegates": delegates,
        "portable_ops": dict(ops.most_common()),
    }
