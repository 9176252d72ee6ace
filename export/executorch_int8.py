"""`e3dpsm convert executorch --quantize int8`: an INT8 step program for XNNPACK through
PT2E (torchao's `prepare_pt2e` / `convert_pt2e` with ExecuTorch's `XNNPACKQuantizer`).

- Calibration is the quantiser's own (quantize/calibration.py): frames of the `train` split,
  each paired with the states a continuous fp32 rollout of the ONNX graph carried into it,
  fed to the step wrapper `torch.export` traces (export/wrapper.StepGraph).
- The recurrent groups stay float, as in `e3dpsm quantize`: the S5 layers (input drive,
  transition, readouts), the Kalman fusion and the embedding that reads the fused-pose
  state. Everything else takes the quantizer's symmetric per-channel 8-bit config.
- The program is judged like an INT8 ONNX graph (quantize/holdout.py, budget.py): on the
  `test` split, which calibration never saw, against the fp32 ONNX graph's poses.
"""
from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from e3dpsm.budget import BudgetCheck
from e3dpsm.data.prepared import PreparedData
from e3dpsm.export.delegation import DELEGATE_CALL, node_macs, op_name
from e3dpsm.export.edge_int8 import EdgeInt8Options, calibration_set, check_artifact, fp32_reference, held_out_set
from e3dpsm.layers.fusion import PoseFusion
from e3dpsm.layers.s5 import S5
from e3dpsm.models import E3DPSM
from e3dpsm.quantize.calibration import CalibrationSet
from e3dpsm.quantize.holdout import HeldOut

# What is quantised: the feature extractor, by module path in the traced wrapper (`model.` is
# StepGraph's attribute), less the recurrent module types inside it. Left float besides: the
# pose heads and the glue between modules (pose prior, mm scaling: an 8-bit pose in mm would be
# rounded to ~8 mm steps), the embedding of the fused-pose state and the Kalman fusion (the
# readout and the recurrence `e3dpsm quantize` keeps float too: e3dpsm/onnx_groups.py).
QUANTISED_SCOPES: tuple[str, ...] = ("model.stem", "model.stages", "model.attention", "model.ssm", "model.decoder")
KEEP_FLOAT_TYPES: tuple[type[torch.nn.Module], ...] = (S5, PoseFusion)
_DEQUANTIZE = "dequantize_per"  # dequantize_per_tensor / _per_channel, ATen or edge dialect


def keep_float_record() -> dict[str, list[str]]:
    """convert.json's account of what was quantised and what was kept float."""
    return {"quantised_scopes": list(QUANTISED_SCOPES), "module_types": [t.__name__ for t in KEEP_FLOAT_TYPES],
            "float_elsewhere": ["direct_head", "delta_head", "pose_embed", "fusion", "pose prior and unit scaling"]}


# The operators that take 8 bits: XNNPACK's quantised convolution and fully connected
# kernels, weights per output channel. Element-wise ops stay float (XNNPACK converts around
# them): measured one step at a time on the trained `small`, quantising the adds too moved
# poses by 57 mm against 13-17 mm without (the reference-point + offset sums of deformable
# attention and the positional sums span far wider ranges than their sources).
QUANTISED_OPERATORS: tuple[Any, ...] = (torch.ops.aten.conv2d.default, torch.ops.aten.linear.default)


def xnnpack_int8_quantizer() -> Any:
    """XNNPACK's quantizer: symmetric 8-bit, weights per output channel, activations per
    tensor (static ranges from calibration), on QUANTISED_OPERATORS inside QUANTISED_SCOPES
    and outside the recurrent module types.

    Configured per operator, not globally: the global config also runs XNNPACK's `cat`
    annotator, which ignores the filter (ExecuTorch 1.5,
    backends/xnnpack/quantizer/xnnpack_quantizer_utils.py `_annotate_cat`) and so put the
    pose, the fused-pose embedding's input and the delta head's operand into 8 bits."""
    from executorch.backends.xnnpack.quantizer.xnnpack_quantizer import (
        XNNPACKQuantizer, get_symmetric_quantization_config)

    class ConvLinearQuantizer(XNNPACKQuantizer):
        def transform_for_annotation(self, model: torch.fx.GraphModule) -> torch.fx.GraphModule:
            # XNNPACK's own turns every scalar operand of add / mul into a float tensor, for its
            # add / mul patterns (off here); it also made the gather attention form's integer
            # index arithmetic float (index_select then refuses the index).
            return model

    config = get_symmetric_quantization_config(is_per_channel=True)
    quantizer = ConvLinearQuantizer()
    for operator in QUANTISED_OPERATORS:
        quantizer.set_operator_type(operator, config)
    for module_type in KEEP_FLOAT_TYPES:
        quantizer.set_module_type(module_type, None)
    # set_module_name refuses None in ExecuTorch 1.5, and its name filter matches whole module
    # paths of called modules (a ModuleList such as `stages` is never called): an allow-list
    # of path prefixes on the innermost module instead.
    return quantizer.set_filter_function(in_quantised_scope)


def in_quantised_scope(node: torch.fx.Node) -> bool:
    """Whether `node` may be quantised. A parameter (get_attr) carries no module path; it
    follows the operator that reads it (the conv annotator filters the weight node too, and a
    path-less weight would keep every convolution float)."""
    if node.op == "get_attr":
        return True
    path = _scope(node)
    return any(path == scope or path.startswith(scope + ".") for scope in QUANTISED_SCOPES)


def step_inputs(calibration: CalibrationSet, input_names: Sequence[str]) -> list[tuple[torch.Tensor, ...]]:
    """The ONNX feed dicts as StepGraph's positional arguments (frame, window, states, in the
    I/O spec's order, which names the ONNX graph's inputs too)."""
    inputs = []
    for feeds in calibration.feeds:
        missing = [name for name in input_names if name not in feeds]
        if missing:
            raise ValueError(f"calibration feeds lack {missing}: recorded from another model's graph")
        inputs.append(tuple(torch.from_numpy(np.ascontiguousarray(feeds[name], dtype=np.float32))
                            for name in input_names))
    return inputs


def calibrator(inputs: Sequence[tuple[torch.Tensor, ...]]) -> Callable[[torch.nn.Module], None]:
    """`calibrate(prepared)` for export_step_program: each recorded step through the observers."""

    def calibrate(prepared: torch.nn.Module) -> None:
        with torch.no_grad():
            for args in inputs:
                prepared(*args)

    return calibrate


def _reads_dequantized(node: torch.fx.Node) -> bool:
    return any(isinstance(a, torch.fx.Node) and _DEQUANTIZE in op_name(a) for a in node.args)


def _scope(node: torch.fx.Node) -> str:
    """The innermost module path of a traced node ("" when the trace kept none)."""
    stack: Mapping[str, Any] = node.meta.get("nn_module_stack") or {}
    paths = [v[0] for v in stack.values()]
    return paths[-1] if paths else ""


def mac_nodes(graph: torch.fx.Graph) -> list[tuple[str, str, bool]]:
    """(operator, module path, reads an 8-bit operand) of every MAC-carrying node of `graph`."""
    return [(op_name(n), _scope(n), _reads_dequantized(n)) for n in graph.nodes
            if n.op == "call_function" and node_macs(n) > 0]


def int8_coverage(edge_manager: Any) -> dict[str, Any]:
    """Which MAC-carrying operators XNNPACK runs on 8-bit operands and which run float (inside
    a delegate or on portable kernels), by operator; and the float ones' module paths."""
    program = edge_manager.exported_program()
    delegated: list[tuple[str, str, bool]] = []
    for child in program.graph_module.children():
        original = getattr(child, "original_module", None)
        if original is not None:
            delegated += mac_nodes(original.graph)
    portable = [m for m in mac_nodes(program.graph) if DELEGATE_CALL not in m[0]]
    return {"xnnpack_int8": dict(Counter(op for op, _, q in delegated if q)),
            "xnnpack_float": dict(Counter(op for op, _, q in delegated if not q)),
            "portable": dict(Counter(op for op, _, _ in portable)),
            "float_modules": sorted({scope for _, scope, q in delegated + portable if not q}),
            "int8_modules": sorted({scope for _, scope, q in delegated + portable if q})}


def convert_executorch_int8(model: E3DPSM, data: PreparedData, path: str | os.PathLike, options: EdgeInt8Options,
                            work: Path, program: Any = None) -> tuple[Any, BudgetCheck, HeldOut]:
    """Write the INT8 program to `path` and judge it: (ExecuTorchResult with the calibration
    and the kept-float modules recorded, the budget check, the held-out frames). `program`:
    ExecuTorchOptions (default: the fp32 converter's)."""
    from e3dpsm.export.edge_export import step_spec
    from e3dpsm.export.executorch_export import ExecuTorchOptions, convert_executorch

    reference = fp32_reference(model, work)
    calibration = calibration_set(reference, data, options)
    inputs = step_inputs(calibration, step_spec(model).input_names)
    record = {"keep_float": keep_float_record(),
              "calibration": {"split": options.split, "frames": len(calibration), "state_source":
                              calibration.state_source, "seconds": round(calibration.seconds, 2)}}
    result = convert_executorch(model, path, program or ExecuTorchOptions(), precision="int8",
                                quantizer=xnnpack_int8_quantizer(), calibrate=calibrator(inputs),
                                extra_record=record)
    held = held_out_set(reference, data, options)
    return result, check_artifact(path, "executorch", held, options), held
