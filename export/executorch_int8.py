"""`e3dpsm convert executorch --quantize int8`: an INT8 step program for XNNPACK through
PT2E (torchao's `prepare_pt2e` / `convert_pt2e` with ExecuTorch's `XNNPACKQuantizer`).

- Calibration is the quantiser's own (quantize/calibration.py): frames of the `train` split,
  each paired with the states a continuous fp32 rollout of the ONNX graph carried into it,
  fed to the step wrapper `torch.export` traces (export/wrapper.StepGraph).
- The recurrent groups stay float, as in `e3dpsm quantize`: the S5 layers (input drive,
  transition, readouts), the Kalman fusion and the embedding that reads the fused-pose
  state. Everything else takes the quantizer's symmetric per-channel 8-bit config.
- Return to float where the budget needs it, as `e3dpsm quantize`'s FP16 search does
  (quantize/place.greedy_groups): the full 8-bit program first, run in PyTorch after PT2E's
  conversion (quantize / dequantize pairs, no lowering) on the `val` split; while it is over
  budget there, the block (stem, each stage, each attention layer, the SSM's projections,
  the decoder) whose return to float lowers the worst upper bound most stays float.
- The program is judged like an INT8 ONNX graph (quantize/holdout.py, budget.py): on the
  `test` split, which neither calibration nor the search saw, against the fp32 ONNX
  graph's poses.
"""
from __future__ import annotations

import functools
import os
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from e3dpsm.budget import BudgetCheck
from e3dpsm.data.prepared import PreparedData
from e3dpsm.export.delegation import module_scope, node_macs, op_name
from e3dpsm.export.edge_int8 import (EdgeInt8Options, calibration_set, check_artifact, fp32_reference, held_out_set,
                                     narrow_float_groups, search_float_groups, search_record, search_set)
from e3dpsm.export.executorch_export import quantized_module
from e3dpsm.layers.fusion import PoseFusion
from e3dpsm.layers.s5 import S5
from e3dpsm.models import E3DPSM, OUTPUT_NAMES
from e3dpsm.quantize.calibration import CalibrationSet
from e3dpsm.quantize.holdout import HeldOut
from e3dpsm.quantize.place import Placement
from e3dpsm.runtime.stepping import StateArrays


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


def xnnpack_int8_quantizer(keep_float: Sequence[str] = ()) -> Any:
    """XNNPACK's quantizer: symmetric 8-bit, weights per output channel, activations per
    tensor (static ranges from calibration), on QUANTISED_OPERATORS inside QUANTISED_SCOPES,
    outside the recurrent module types and outside the module paths of `keep_float` (the
    search's choice).

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
    return quantizer.set_filter_function(functools.partial(in_quantised_scope, keep_float=tuple(keep_float)))


def in_quantised_scope(node: torch.fx.Node, keep_float: Sequence[str] = ()) -> bool:
    """Whether `node` may be quantised: inside QUANTISED_SCOPES and outside `keep_float`. A
    parameter (get_attr) carries no module path; it follows the operator that reads it (the
    conv annotator filters the weight node too, and a path-less weight would keep every
    convolution float)."""
    if node.op == "get_attr":
        return True
    path = module_scope(node)
    return _under(path, QUANTISED_SCOPES) and not _under(path, keep_float)


def _under(path: str, scopes: Sequence[str]) -> bool:
    return any(path == scope or path.startswith(scope + ".") for scope in scopes)


def search_groups(model: E3DPSM) -> list[tuple[str, list[str]]]:
    """The search's units, (name, [module path]) in the traced wrapper: each member of a
    quantised scope that is a list of blocks (a stage, an attention layer), the other scopes
    whole; only those holding a convolution or linear layer that would take 8 bits."""
    groups = []
    for scope in QUANTISED_SCOPES:
        module = model.get_submodule(scope.removeprefix("model."))
        members = ([(f"{scope}.{name}", child) for name, child in module.named_children()]
                   if isinstance(module, torch.nn.ModuleList) else [(scope, module)])
        groups += [(path, [path]) for path, child in members if _quantisable_layers(child)]
    return groups


def _quantisable_layers(module: torch.nn.Module) -> int:
    kept = [m for m in module.modules() if isinstance(m, KEEP_FLOAT_TYPES)]
    inside_kept = {id(m) for k in kept for m in k.modules()}
    return sum(1 for m in module.modules()
               if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear)) and id(m) not in inside_kept)


class QuantizedModuleStepper:
    """A PT2E-converted step module (export/executorch_export.quantized_module) behind the
    stepping protocol: the search runs it in PyTorch, with the quantisation's rounding, over
    frames with states carried, as check_stepper runs any runtime."""

    def __init__(self, module: torch.fx.GraphModule, model: E3DPSM) -> None:
        self.module, self.model = module, model
        self.state_names = [s.name for s in model.state_spec()]

    def init_state(self, batch: int = 1) -> StateArrays:
        return {k: v.numpy() for k, v in self.model.init_state(batch).items()}

    @torch.no_grad()
    def step(self, lnes: np.ndarray, state: Mapping[str, np.ndarray],
             window_ms: float) -> tuple[dict[str, np.ndarray], StateArrays]:
        window = torch.full((lnes.shape[0],), float(window_ms))
        out = self.module(torch.from_numpy(lnes), window, *(torch.from_numpy(state[n]) for n in self.state_names))
        poses, states = out[:len(OUTPUT_NAMES)], out[len(OUTPUT_NAMES):]
        return ({n: v.numpy() for n, v in zip(OUTPUT_NAMES, poses)},
                {n: v.numpy() for n, v in zip(self.state_names, states)})


SEARCH_RUNTIME = "PyTorch (PT2E)"


def _trial(model: E3DPSM, program: Any, calibrate: Callable[[torch.nn.Module], None]) -> Callable[[Sequence[str]], Any]:
    """trial(floats): the program converted with the module paths `floats` float, stepped in PyTorch."""
    return lambda floats: QuantizedModuleStepper(quantized_module(program, xnnpack_int8_quantizer(floats), calibrate),
                                                 model)


def search_keep_float(model: E3DPSM, program: Any, calibrate: Callable[[torch.nn.Module], None],
                      search: HeldOut, options: EdgeInt8Options) -> Placement:
    """Which blocks stay float for the program to meet the budget on `search` (module doc):
    edge_int8.search_float_groups over search_groups, each trial a converted module run in PyTorch."""
    return search_float_groups([name for name, _ in search_groups(model)], _trial(model, program, calibrate),
                               search, options, SEARCH_RUNTIME)


def operator_units(model: E3DPSM, group: str, program: torch.export.ExportedProgram | None = None) -> list[str]:
    """The module paths of the convolutions and linear layers of `group` that would take 8
    bits (with `program`: only those its graph calls; the export folds some), largest weights
    first: the units the narrowing returns to 8 bits one at a time
    (edge_int8.narrow_float_groups; keep-float names are module paths, in_quantised_scope)."""
    module = model.get_submodule(group.removeprefix("model."))
    inside_kept = {id(m) for k in module.modules() if isinstance(k, KEEP_FLOAT_TYPES) for m in k.modules()}
    computed = None if program is None else {module_scope(n) for n in program.graph_module.graph.nodes
                                              if n.op == "call_function"}
    layers = [(f"{group}.{name}", m.weight.numel()) for name, m in module.named_modules()
              if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear)) and id(m) not in inside_kept
              and (computed is None or f"{group}.{name}" in computed)]
    return [path for path, _ in sorted(layers, key=lambda layer: -layer[1])]


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


def _runs_in_8_bits(node: torch.fx.Node) -> bool:
    """Input and weight both arrive dequantized. One dequantized operand is not enough: a float
    operator reading an 8-bit neighbour's output (a decomposed LayerNorm's matmul, a kept-float
    convolution after a quantised one) gets a dequantized activation and runs in float."""
    operands = node.args[:2]
    return len(operands) == 2 and all(isinstance(a, torch.fx.Node) and _DEQUANTIZE in op_name(a) for a in operands)


def mac_nodes(graph: torch.fx.Graph) -> list[tuple[str, str, bool]]:
    """(operator, module path, runs in 8 bits) of every MAC-carrying node of `graph`."""
    return [(op_name(n), module_scope(n), _runs_in_8_bits(n)) for n in graph.nodes
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
    portable = mac_nodes(program.graph)  # a delegate call carries no MACs of its own (node_macs)
    return {"xnnpack_int8": dict(Counter(op for op, _, q in delegated if q)),
            "xnnpack_float": dict(Counter(op for op, _, q in delegated if not q)),
            "portable": dict(Counter(op for op, _, _ in portable)),
            "float_modules": sorted({scope for _, scope, q in delegated + portable if not q}),
            "int8_modules": sorted({scope for _, scope, q in delegated + portable if q})}


def convert_executorch_int8(model: E3DPSM, data: PreparedData, path: str | os.PathLike, options: EdgeInt8Options,
                            work: Path, program: Any = None, taps: bool = False) -> tuple[Any, BudgetCheck, HeldOut]:
    """Write the INT8 program to `path` and judge it: (ExecuTorchResult with the calibration
    and the kept-float modules recorded, the budget check, the held-out frames). `program`:
    ExecuTorchOptions (default: the fp32 converter's). `taps`: also its taps program beside it
    (export/executorch_taps.py), checked against it here (`result.taps`)."""
    from e3dpsm.export.edge_export import export_ready, step_spec
    from e3dpsm.export.executorch_export import ExecuTorchOptions, convert_executorch, step_program

    program = program or ExecuTorchOptions()
    reference = fp32_reference(model, work)
    calibration = calibration_set(reference, data, options)
    calibrate = calibrator(step_inputs(calibration, step_spec(model).input_names))
    record: dict[str, Any] = {
        "keep_float": keep_float_record(),
        "calibration": {"split": options.split, "frames": len(calibration), "state_source":
                        calibration.state_source, "seconds": round(calibration.seconds, 2)},
        "budget": options.budget.to_dict()}
    keep_float: tuple[str, ...] = ()
    if options.search_rounds > 0:
        search = search_set(reference, data, options)
        with export_ready(model, program.attention_form):  # the graph the program will be lowered from
            traced = step_program(model, program)
            placement = search_keep_float(model, traced, calibrate, search, options)
            keep_float = placement.float_nodes
            record["search"] = search_record(placement, search, options, SEARCH_RUNTIME)
            if keep_float and options.narrow_trials != 0:  # --narrow-trials 0: the blocks stay float whole
                units = {group: operator_units(model, group, traced) for group in keep_float}
                narrowing = narrow_float_groups(keep_float, units, _trial(model, traced, calibrate), search,
                                                options, SEARCH_RUNTIME)
                keep_float = tuple(narrowing.floats)
                record["search"].update(narrowing.search_fields(placement.float_nodes))
        record["keep_float"]["searched"] = list(keep_float)
    result = convert_executorch(model, path, program, precision="int8",
                                quantizer=xnnpack_int8_quantizer(keep_float), calibrate=calibrate,
                                extra_record=record)
    if taps:
        result.taps = write_taps_program(model, path, program, keep_float, calibrate, record, calibration,
                                         options.threads)
    held = held_out_set(reference, data, options)
    return result, check_artifact(path, "executorch", held, options), held


TAPS_CHECK_STEPS = 32  # calibration frames both programs step through, states carried, before the taps are trusted


def write_taps_program(model: E3DPSM, path: str | os.PathLike, program: Any, keep_float: Sequence[str],
                       calibrate: Callable[[torch.nn.Module], None], record: dict[str, Any],
                       calibration: CalibrationSet, threads: int | None) -> dict[str, Any]:
    """The taps program of the INT8 program at `path` (the same quantizer, calibration and
    kept-float modules: PT2E's observers are deterministic, so the same codes), written beside
    it and checked to compute its poses and states bit for bit here; a ValueError otherwise."""
    from e3dpsm.export.edge_export import step_spec
    from e3dpsm.export.executorch_export import convert_executorch
    from e3dpsm.export.executorch_taps import steps_identical, taps_path
    from e3dpsm.export.onnx_export import ExportError

    twin = taps_path(path)
    written = convert_executorch(model, twin, program, precision="int8", quantizer=xnnpack_int8_quantizer(keep_float),
                                 calibrate=calibrate, extra_record={**record, "taps_of": Path(path).name}, taps=True)
    frame_name, window_name = step_spec(model).input_names[:2]
    feeds = calibration.feeds[:TAPS_CHECK_STEPS]
    same = steps_identical(path, twin, [f[frame_name] for f in feeds], [float(f[window_name][0]) for f in feeds],
                           threads)
    if same < len(feeds):
        raise ExportError(f"the taps program {twin} parts from {Path(path).name} at step {same} on this host: it "
                         "would not describe the program shipped; convert again without --taps")
    return {"file": Path(twin).name, "bytes": written.bytes, "taps": written.taps["count"],
            "identical_steps": same, "seconds": written.seconds["total"]}
