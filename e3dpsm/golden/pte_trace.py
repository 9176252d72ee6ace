"""Where one `.pte` program's computation parts between two machines (this host and an ARM
device, emulated or real): the ExecuTorch counterpart of tflite_trace.py, propagated only.

ExecuTorch's event tracer (ETDump, with a debug buffer) keeps the output of every instruction
a program runs: each kernel outside a delegate and each delegate call, an XNNPACK partition
whose inside it does not show (its profiling events name the XNNPACK operators it ran, in
order). Each side steps the program over the golden's frames with its own states carried and
keeps an 8-byte digest of every instruction output at every step; `compare` names the first
step where any output differs and the outputs that part first, in execution order: the first
of them reads only what agreed (the step's earlier outputs and the states carried from the
previous step, which agreed too), so the arithmetic of its instruction is where the two
machines part. The trace narrows to a partition, not to one operator inside it.

    python -m e3dpsm.golden.pte_trace record step_int8.pte GOLDEN host.json [--steps N]
    python -m e3dpsm.golden.pte_trace record step_int8.pte GOLDEN device.json  # on the device
    python -m e3dpsm.golden.pte_trace compare host.json device.json
"""
from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from e3dpsm.golden.trace_files import (TraceKind, departure_line, digest, first_steps_apart, read_record,
                                       trace_main)

# The debug buffer of the first step, which runs alone (record): ample for `small` and `paper`
# (what one step logs, every instruction output, is a few MB); later loads are sized from it.
FIRST_STEP_DEBUG_BYTES = 256 << 20
CHUNK_STEPS = 16
NO_EVENT_TRACER_EXIT = 3  # `record` on a runtime without the event tracer (arm_emulation.py tells it apart)
# ETDump's scalar types (executorch/devtools/etdump/schema_flatcc.py ScalarType) -> bytes each
_ITEM_BYTES = {0: 1, 1: 1, 2: 2, 3: 4, 4: 8, 5: 2, 6: 4, 7: 8, 11: 1, 15: 2}
DELEGATE_CALL = "DELEGATE_CALL"
METHOD_EXECUTE = "Method::execute"
PROGRAM_OUTPUT = "(program output)"
TRACE = TraceKind(name="pte_trace", items="outputs", key="instruction", what="outputs",
                  described="instruction outputs")


def _used(ends: list[int]) -> int:
    """Bytes of the debug buffer up to the last tensor's end (its start and any padding counted)."""
    return max(ends[1::2], default=0)


def _value_bytes(value: Any, debug: bytes, ends: list[int] | None = None) -> list[bytes]:
    """The bytes of one ETDump debug value (a tensor, a tensor list, or a scalar); each tensor's
    start and end in the buffer appended to `ends`."""
    tensors = [value.tensor] if value.tensor is not None else list(value.tensor_list.tensors) if value.tensor_list \
        else []
    if not tensors:
        scalars = (value.int_value, value.float_value, value.double_value, value.bool_value)
        return [repr([s for s in scalars if s is not None]).encode()]
    chunks = []
    for tensor in tensors:
        scalar = int(getattr(tensor.scalar_type, "value", tensor.scalar_type))
        if scalar not in _ITEM_BYTES:
            raise ValueError(f"ETDump tensor of scalar type {scalar}: not one this trace reads")
        count = int(np.prod(tensor.sizes)) if tensor.sizes else 1
        end = tensor.offset + count * _ITEM_BYTES[scalar]
        if end > len(debug):
            raise ValueError(f"ETDump tensor at bytes {tensor.offset}-{end} past its {len(debug)}-byte debug buffer")
        if ends is not None:
            ends += [tensor.offset, end]
        chunks.append(debug[tensor.offset:end])
    return chunks


def instruction_outputs(etdump: bytes, debug: bytes) -> tuple[list[dict[str, Any]], list[list[str]], int]:
    """(one record per value a step logs, in execution order: its instruction, what ran it and,
    for a partition, its XNNPACK operators; the digests of each step's values; the debug
    buffer's bytes one step used) from an ETDump written after the steps (its first run is
    the method's loading)."""
    from executorch.devtools.etdump.serialize import deserialize_from_etdump_flatcc

    runs = [run for run in deserialize_from_etdump_flatcc(etdump).run_data
            if any(event.debug_event is not None for event in run.events)]
    outputs: list[dict[str, Any]] = []
    digests: list[list[str]] = []
    used = 0
    for index, run in enumerate(runs):
        found, step = [], []
        names: dict[int, str] = {}
        operators: dict[int, list[str]] = {}
        for event in run.events:
            profile = event.profile_event
            if profile is None:
                continue
            if profile.delegate_debug_id_str:
                operators.setdefault(profile.instruction_id, []).append(profile.delegate_debug_id_str)
            elif profile.name and profile.name.startswith("native_call_"):
                names[profile.instruction_id] = profile.name.removeprefix("native_call_")
            elif profile.name == DELEGATE_CALL:
                names.setdefault(profile.instruction_id, DELEGATE_CALL)
        logged: dict[int, int] = {}
        ends: list[int] = []
        returned = False  # the values logged after the method's own event are what it returns
        for event in run.events:
            if event.profile_event is not None and event.profile_event.name == METHOD_EXECUTE:
                returned = True
            debug_event = event.debug_event
            if debug_event is None:
                continue
            instruction = -1 if returned else int(debug_event.instruction_id)
            kernel = PROGRAM_OUTPUT if returned else names.get(instruction, "?")
            for chunk in _value_bytes(debug_event.debug_entry, debug, ends):
                logged[instruction] = logged.get(instruction, -1) + 1  # an instruction may log several values
                found.append({"instruction": instruction, "output": logged[instruction], "kernel": kernel,
                              "operators": len(operators.get(instruction, [])),
                              "operator_names": operators.get(instruction, [])})
                step.append(digest(chunk))
        if index == 0:
            outputs = found
        elif _keys(found) != _keys(outputs):
            raise ValueError(f"step {index} ran other instructions than step 0: not one program's steps")
        used = max(used, _used(ends))
        digests.append(step)
    return outputs, digests, used


def record(model: str | os.PathLike, golden_dir: str | os.PathLike, steps: int | None = None,
           threads: int | None = 1) -> dict[str, Any]:
    """Step `model` over the golden's frames (states carried by this runtime) with ETDump's
    debug buffer on; every instruction output's digest at every step, and where this ran.

    ExecuTorch aborts the process when the debug buffer overflows, so the first step runs alone
    with FIRST_STEP_DEBUG_BYTES and the rest in chunks of CHUNK_STEPS, each program load sized
    from what the first step used (every step of a program logs the same tensors)."""
    from e3dpsm.errors import InputError
    from e3dpsm.golden.store import load_golden
    from e3dpsm.runtime.executorch_session import ExecuTorchStepSession
    from e3dpsm.utils.isa import detect_isa

    if steps is not None and steps < 1:
        raise InputError(f"--steps {steps}: a trace needs at least one step")
    golden = load_golden(golden_dir)
    count = golden.steps if steps is None else min(steps, golden.steps)
    session = ExecuTorchStepSession(model, threads=threads)  # the contract: inputs, outputs, states
    state = session.init_state(1)
    outputs: list[dict[str, Any]] | None = None
    digests: list[list[str]] = []
    per_step = FIRST_STEP_DEBUG_BYTES
    while len(digests) < count:
        first = len(digests)
        chunk = 1 if first == 0 else min(CHUNK_STEPS, count - first)
        traced = _traced_module(model, per_step * chunk)
        session.use_method(_Traced(traced))  # the same program, stepped through the traced module
        for step in range(first, first + chunk):
            _, state = session.run_feeds(session.feeds(golden.frame(step), state, golden.window_ms(step)))
        found, rows, used = _written(traced)
        if outputs is None:
            outputs, per_step = found, used + used // 4 + (1 << 16)
        elif _keys(found) != _keys(outputs):
            raise ValueError(f"steps from {first} ran other instructions than step 0: not one program's steps")
        if len(rows) != chunk:
            raise ValueError(f"ETDump holds {len(rows)} of steps {first}-{first + chunk - 1}")
        digests += rows
    return {"model": str(model), "steps": count, "outputs": outputs, "digests": digests,
            "isa": detect_isa().to_dict()}


def _traced_module(model: str | os.PathLike, debug_bytes: int) -> Any:
    from executorch.extension.pybindings.portable_lib import _load_for_executorch

    return _load_for_executorch(str(model), enable_etdump=True, debug_buffer_size=int(debug_bytes))


def _written(traced: Any) -> tuple[list[dict[str, Any]], list[list[str]], int]:
    with tempfile.TemporaryDirectory(prefix="e3dpsm-pte-trace-") as work:
        etdump, debug = Path(work) / "trace.etdump", Path(work) / "trace.debug"
        traced.write_etdump_result_to_file(str(etdump), str(debug))
        if not etdump.is_file():
            raise NoEventTracer(f"this ExecuTorch runtime ({_release()}) records no ETDump: it was built without "
                                "its event tracer (EXECUTORCH_ENABLE_EVENT_TRACER); trace with one that has it")
        return instruction_outputs(etdump.read_bytes(), debug.read_bytes())


class NoEventTracer(RuntimeError):
    """The runtime was built without ExecuTorch's event tracer: nothing to trace with."""


def _release() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"executorch {version('executorch')}"
    except PackageNotFoundError:
        return "executorch, release unknown"


def _keys(outputs: list[dict[str, Any]]) -> list[tuple[int, int]]:
    return [(o["instruction"], o["output"]) for o in outputs]


class _Traced:
    """ExecuTorchStepSession's method interface over the ETDump-enabled module."""

    def __init__(self, module: Any) -> None:
        self.module = module

    def execute(self, inputs: list[Any]) -> list[Any]:
        return self.module.forward(inputs)


def read_trace(path: str | os.PathLike) -> dict[str, Any]:
    """A record written by `record`, checked for what `compare` reads (trace_files.read_record)."""
    return read_record(path, TRACE)


def compare(host: dict[str, Any], device: dict[str, Any]) -> dict[str, Any]:
    """Each instruction output's first step apart (None: the same at every step both ran), and
    the outputs that part first, in execution order."""
    key = lambda o: (o["instruction"], o["output"])  # noqa: E731
    if [key(o) for o in host["outputs"]] != [key(o) for o in device["outputs"]]:
        raise ValueError("the two traces are of different programs (their instructions differ)")
    apart = first_steps_apart(host, device, TRACE, position=True)
    return {"steps": apart["steps"], "outputs": len(apart["items"]), "apart_by_end": apart["apart_by_end"],
            "first_step": apart["first_step"], "first_departures": apart["first_departures"],
            "per_output": apart["items"], "host_isa": host["isa"], "device_isa": device["isa"]}


def describe(output: dict[str, Any]) -> str:
    """`instruction 19 (XNNPACK partition of 75 operators, 9 of them 8-bit; value 3)`,
    `instruction 4 (grid_sampler_2d.out)` or `(program output) 283`."""
    if output["kernel"] == PROGRAM_OUTPUT:
        return f"{PROGRAM_OUTPUT} {output['position']}"
    if output["kernel"] != DELEGATE_CALL:
        return f"instruction {output['instruction']} ({output['kernel']})"
    names = output.get("operator_names") or []
    integer = sum(1 for n in names if "QS8" in n or "QC8" in n or "QU8" in n)
    return (f"instruction {output['instruction']} (XNNPACK partition of {output['operators']} operators, "
            f"{integer} of them 8-bit; value {output['output']})")


def summary(report: dict[str, Any]) -> str:
    """One line: where the outputs part first, or that they never do."""
    return departure_line(report, report["outputs"], "instruction outputs", "in execution order", describe,
                          "after it at that step")


def main(argv: Sequence[str] | None = None) -> int:
    return trace_main(argv, TRACE, __doc__, record=record, compare=compare, summary=summary,
                      record_help="digests of every instruction output at every golden step, on this machine",
                      compare_help="where two machines' instruction outputs part (host first)",
                      exit_codes={NoEventTracer: NO_EVENT_TRACER_EXIT})


if __name__ == "__main__":
    sys.exit(main())
