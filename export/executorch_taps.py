"""The taps of an INT8 `.pte`: the same program with the 8-bit codes of every quantised
activation also returned as program outputs (`step_taps.pte` beside `step.pte`), so that a
device whose ExecuTorch runtime has no event tracer (PyPI's aarch64 wheels; pte_trace.py needs
one) still shows where its arithmetic parts from the host's: e3dpsm/golden/pte_taps.py digests
the extra outputs at every step on both machines and names the first activation apart.

A tap is the output of an activation's quantize op in PT2E's converted module (a weight's is
folded into a constant and never a tap). Returning it changes no value: the program computes
what `step.pte` computes, XNNPACK's partitions hand the codes out as they are, and the
converter checks that on this host, the taps program's poses and states equal the shipped
program's bit for bit at every checked step (convert_executorch_int8); a program that did not
would say nothing about the one shipped and is refused.

The taps, in the order the program returns them, travel in the program as the constant method
TAPS_METHOD (JSON; runtime/artifact_metadata.py), so the device reads them without torch.fx or
onnx (golden/pte_taps.py): each its name, `<module path>:<node>`, and its segment, the
operators between the codes it reads and it.
"""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np
import torch

TAPS_SUFFIX = "_taps"  # step.pte -> step_taps.pte
_QUANTIZE = "quantize_per_tensor"


def taps_path(path: str | os.PathLike) -> str:
    """Where the taps program of the INT8 program `path` is written: `step.pte` -> `step_taps.pte`."""
    root, ext = os.path.splitext(os.fspath(path))
    return f"{root}{TAPS_SUFFIX}{ext}"


def activation_quantizes(graph: torch.fx.Graph) -> list[torch.fx.Node]:
    """The quantize ops of `graph` whose input is computed (an activation), in graph order; a
    quantize of a parameter (`get_attr`) is a weight's."""
    return [n for n in graph.nodes
            if n.op == "call_function" and _QUANTIZE in str(n.target) and "dequantize" not in str(n.target)
            and isinstance(n.args[0], torch.fx.Node) and n.args[0].op != "get_attr"]


def tap_name(node: torch.fx.Node) -> str:
    """`<innermost module path>:<the quantised op's node name>` ("" for the path when the trace kept none)."""
    from e3dpsm.export.delegation import module_scope

    source = node.args[0]
    return f"{module_scope(source)}:{source.name}"


def tap_segment(node: torch.fx.Node) -> list[str]:
    """The operators between the codes and constants a tap's quantize reads (dequantize ops,
    program inputs, parameters) and it, in graph order, by ATen name (`softmax`, `conv2d`):
    the arithmetic a tap that parts first points at."""
    from e3dpsm.export.delegation import op_name

    inside: set[torch.fx.Node] = set()
    stack = [node.args[0]]
    while stack:
        current = stack.pop()
        if current in inside or current.op != "call_function" or "dequantize" in op_name(current):
            continue
        inside.add(current)
        stack.extend(current.all_input_nodes)
    order = {n: k for k, n in enumerate(node.graph.nodes)}
    return [op_name(n).removeprefix("aten.").split(".")[0] for n in sorted(inside, key=order.__getitem__)]


def with_taps(module: torch.fx.GraphModule) -> tuple[torch.fx.GraphModule, list[dict[str, object]]]:
    """`module` (PT2E-converted, changed in place) returning its outputs and then the 8-bit
    codes of every activation quantize, and the taps in that order: `{"tap": name, "segment":
    operators}`. Its inputs and outputs become flat positional tuples (torch.export traces it
    again as it traced the step wrapper: lnes, window, states)."""
    taps = activation_quantizes(module.graph)
    if not taps:
        raise ValueError("the module has no quantised activation to tap: tap a PT2E-converted INT8 module")
    output = next(n for n in module.graph.nodes if n.op == "output")
    returned = output.args[0]
    if not isinstance(returned, (tuple, list)):
        raise ValueError("the module returns one value, not the step wrapper's tuple of poses and states")
    output.args = ((*returned, *taps),)
    module.graph._codegen = torch.fx.graph.CodeGen()  # flat in and out: the pytree specs named the old outputs
    module.recompile()
    return module, [{"tap": tap_name(n), "segment": tap_segment(n)} for n in taps]


def steps_identical(shipped: str | os.PathLike, taps: str | os.PathLike, frames: Sequence[np.ndarray],
                    windows: Sequence[float], threads: int | None = 1) -> int:
    """How many of the steps over `frames` (states carried by each program) the taps program's
    poses and states equal the shipped program's bit for bit, before the first that differs."""
    from e3dpsm.runtime.executorch_session import ExecuTorchStepSession

    one, two = (ExecuTorchStepSession(p, threads=threads) for p in (shipped, taps))
    state_one, state_two = one.init_state(1), two.init_state(1)
    for step, (frame, window) in enumerate(zip(frames, windows)):
        out_one, state_one = one.step(frame, state_one, window)
        out_two, state_two = two.step(frame, state_two, window)
        values_one = [*out_one.values(), *state_one.values()]
        values_two = [*out_two.values(), *state_two.values()]
        if list(out_one) != list(out_two) or not all(np.array_equal(a, b) for a, b in zip(values_one, values_two)):
            return step
    return len(frames)
