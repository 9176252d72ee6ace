"""Every node of an exported step graph in a module group of profiles.flops: the module
scope `e3dpsm.onnx_groups.module_scopes` finds (`stages.0`, `ssm`, `delta_head`, ...)
mapped onto the paper's coarser groups (`cnn`, `ssm`, `heads`, ...)."""
from __future__ import annotations

from typing import Mapping

import onnx

from e3dpsm.onnx_groups import module_scopes
from e3dpsm.profiles.flops import group_of


def assign_groups(model: onnx.ModelProto, dtypes: Mapping[str, int]) -> dict[str, str]:
    """node key (name, or first output if unnamed) -> group name (flops.OTHER for none)."""
    # A scope's attribute is its name before the index (`stages.0` -> `stages`).
    return {key: group_of(scope.split(".", 1)[0]) for key, scope in module_scopes(model, dtypes).items()}
