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

import onnx
from onnx import TensorProto

from e3dpsm.onnx_graph import GraphIndex
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


def assign_groups(model: onnx.ModelProto, dtypes: dict[str, int]) -> dict[str, str]:
    """node key (name, or first output if unnamed) -> group name."""
    index = GraphIndex(model)

    def is_activation(tensor: str) -> bool:
        return dtypes.get(tensor, TensorProto.FLOAT) in _DATA_TYPES

    def neighbours(key: str) -> list[str]:
        return index.producers_of(key, is_activation) + index.consumers_of(key, is_activation)

    labels: dict[str, str | None] = {
        key: next((g for g in map(scope_group, [node.name, *node.output]) if g), None)
        for key, node in index.nodes.items()}

    # S5 anchors and their unscoped neighbourhood.
    queue = [key for key, node in index.nodes.items() if labels[key] is None and any(
        t.startswith(_SSM_STATE_PREFIX) for t in (*node.input, *node.output))]
    for key in queue:
        labels[key] = "ssm"
    while queue:
        for other in neighbours(queue.pop()):
            if labels[other] is None and index.nodes[other].op_type != "Constant":
                labels[other] = "ssm"
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
