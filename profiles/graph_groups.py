"""Assign every node of an exported step graph to a module group of profiles.flops.

1. Scope: the legacy tracer names nodes after the PyTorch module path (`/stages.0/block1/
   conv1/Conv`, `/decoder/layers.0/...`); onnxsim's fused nodes (`Gemm_27`) often keep the
   scope in their output name (`/delta_head/Add_output_0`).
2. S5 anchors: the model calls its S5 blocks through `block.step(...)`, which the tracer does
   not scope, so their nodes carry bare names (`/Mul_3`, `/norm1/...`). Nodes reading or
   writing an `s5_*` state are S5 work, and so is every unscoped node connected to them by
   activation tensors (float or 8-bit; int64 shape arithmetic is shared: not followed).
3. The remaining unscoped nodes take the group their labelled producers agree on, else
   the one their consumers agree on (repeated until nothing changes); leftovers are "other".
"""
from __future__ import annotations

from collections import defaultdict

import onnx
from onnx import TensorProto

from e3dpsm.profiles.flops import OTHER, group_of

# Activation types: float, and 8-bit for the quantised tensors of QDQ graphs. int64 / int32
# tensors are shape arithmetic, shared across modules, so labels never travel along them.
_DATA_TYPES = {TensorProto.FLOAT, TensorProto.FLOAT16, TensorProto.DOUBLE, TensorProto.BFLOAT16,
               TensorProto.UINT8, TensorProto.INT8}
_SSM_STATE_PREFIX = "s5_"


def scope_group(name: str) -> str | None:
    """Group of the first module-path component of a node or tensor name, if any."""
    if not name.startswith("/"):
        return None
    for component in name[1:].split("/")[:-1]:  # the last component is the op or tensor name
        group = group_of(component.split(".", 1)[0])
        if group != OTHER:
            return group
    return None


def node_key(node: onnx.NodeProto) -> str:
    return node.name or node.output[0]


def assign_groups(model: onnx.ModelProto, dtypes: dict[str, int]) -> dict[str, str]:
    """node key (name, or first output if unnamed) -> group name."""
    nodes = list(model.graph.node)

    def is_activation(tensor: str) -> bool:
        return dtypes.get(tensor, TensorProto.FLOAT) in _DATA_TYPES

    producer: dict[str, int] = {}
    consumers: dict[str, list[int]] = defaultdict(list)
    for i, node in enumerate(nodes):
        for tensor in node.output:
            producer[tensor] = i
        for tensor in node.input:
            consumers[tensor].append(i)

    def data_producers(i: int) -> list[int]:
        return [producer[t] for t in nodes[i].input if t in producer and is_activation(t)]

    def data_consumers(i: int) -> list[int]:
        return [j for t in nodes[i].output if is_activation(t) for j in consumers.get(t, ())]

    labels: list[str | None] = []
    for node in nodes:
        found = next((g for g in map(scope_group, [node.name, *node.output]) if g), None)
        labels.append(found)

    # S5 anchors and their unscoped neighbourhood.
    queue = [i for i, node in enumerate(nodes) if labels[i] is None and any(
        t.startswith(_SSM_STATE_PREFIX) for t in (*node.input, *node.output))]
    for i in queue:
        labels[i] = "ssm"
    while queue:
        i = queue.pop()
        for j in (*data_producers(i), *data_consumers(i)):
            if labels[j] is None and nodes[j].op_type != "Constant":
                labels[j] = "ssm"
                queue.append(j)

    changed = True
    while changed:
        changed = False
        for i in range(len(nodes)):
            if labels[i] is not None:
                continue
            for neighbours in (data_producers(i), data_consumers(i)):
                found = {labels[j] for j in neighbours if labels[j] is not None}
                if len(found) == 1:
                    labels[i] = found.pop()
                    changed = True
                    break
    return {node_key(node): label or OTHER for node, label in zip(nodes, labels)}
