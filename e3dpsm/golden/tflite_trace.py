"""Where one INT8 `.tflite`'s 8-bit codes part between two machines (this host and an ARM
device, emulated or real): the `.tflite` counterpart of the ONNX kernel-parity trace
(kernel_trace.py), propagated only.

Inside an XNNPACK partition LiteRT shows no intermediate tensor, so the trace runs a copy of
the artifact whose every QUANTIZE output (the 8-bit code an integer kernel reads) is also an
output of the graph and of its signature (`e3dpsm_code_<k>`); XNNPACK then hands those codes
out at each step. Each side steps that copy over the golden's frames with its own states
carried and keeps a digest of every code tensor at every step (8 bytes each: the host's file
stays small, the device needs no host arrays); `compare` names the first step where any code
tensor differs and which ones, with the operator that produced the float values the
QUANTIZE rounded (a float kernel whose last bits differ between ISAs flips a code there).
Torch-free: ai-edge-litert and numpy, as on a device.

    python -m e3dpsm.golden.tflite_trace record step_int8.tflite GOLDEN host.json [--steps N]
    python -m e3dpsm.golden.tflite_trace record step_int8.tflite GOLDEN device.json  # on the device
    python -m e3dpsm.golden.tflite_trace compare host.json device.json
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

CODE_PREFIX = "e3dpsm_code_"


def _op_names() -> dict[int, str]:
    from ai_edge_litert import schema_py_generated as schema

    return {v: k for k, v in vars(schema.BuiltinOperator).items() if not k.startswith("_")}


def with_exposed_codes(content: bytes) -> tuple[bytes, list[dict[str, Any]]]:
    """(the flatbuffer with every QUANTIZE output of subgraph 0 also a graph and signature
    output, one record per code: its output name, tensor, the QUANTIZE's operator index, the
    operator types that produced its input and that read it)."""
    from ai_edge_litert import schema_py_generated as schema

    from e3dpsm.runtime.tflite_metadata import rewrite_model

    names = _op_names()
    codes: list[dict[str, Any]] = []

    def edit(model: Any) -> None:
        graph = model.subgraphs[0]

        def op_type(op: Any) -> str:
            code = model.operatorCodes[op.opcodeIndex]
            return names.get(max(code.builtinCode, code.deprecatedBuiltinCode), "CUSTOM")

        producer = {int(t): op_type(op) for op in graph.operators for t in op.outputs}
        readers: dict[int, list[str]] = {}
        for op in graph.operators:
            for t in op.inputs:
                readers.setdefault(int(t), []).append(op_type(op))
        outputs = [int(t) for t in graph.outputs]
        signature = model.signatureDefs[0]
        for index, op in enumerate(graph.operators):
            if op_type(op) != "QUANTIZE":
                continue
            tensor = int(op.outputs[0])
            name = f"{CODE_PREFIX}{len(codes)}"
            codes.append({"name": name, "tensor": tensor, "tensor_name": graph.tensors[tensor].name.decode(),
                          "operator": index, "fed_by": producer.get(int(op.inputs[0]), "(graph input)"),
                          "read_by": sorted(set(readers.get(tensor, [])))})
            if tensor not in outputs:
                outputs.append(tensor)
            entry = schema.TensorMapT()
            entry.name, entry.tensorIndex = name, tensor
            signature.outputs.append(entry)
        graph.outputs = outputs

    return rewrite_model(content, edit), codes


def record(model: str | os.PathLike, golden_dir: str | os.PathLike, steps: int | None = None,
           threads: int | None = 1) -> dict[str, Any]:
    """Step the code-exposing copy of `model` over the golden's frames (states carried by this
    runtime); every code tensor's digest at every step, and where this ran."""
    from e3dpsm.errors import InputError
    from e3dpsm.golden.store import load_golden
    from e3dpsm.runtime.litert_session import LiteRTStepSession, read_tflite
    from e3dpsm.utils.isa import detect_isa

    if steps is not None and steps < 1:
        raise InputError(f"--steps {steps}: a trace needs at least one step")
    content, codes = with_exposed_codes(read_tflite(model))
    golden = load_golden(golden_dir)
    count = golden.steps if steps is None else min(steps, golden.steps)
    with tempfile.TemporaryDirectory(prefix="e3dpsm-tflite-trace-") as work:
        path = Path(work) / "exposed.tflite"
        path.write_bytes(content)
        session = LiteRTStepSession(path, threads=threads)
        state, digests = session.init_state(1), []
        for step in range(count):
            raw = session._run_one(session.feeds(golden.frame(step), state, golden.window_ms(step)))
            state = {s.name: raw[s.output_name] for s in session.meta.states}
            digests.append([digest(np.ascontiguousarray(raw[c["name"]]).tobytes())
                            for c in codes])
    return {"model": str(model), "steps": count, "codes": codes, "digests": digests, "isa": detect_isa().to_dict()}


TRACE = TraceKind(name="tflite_trace", items="codes", key="name", what="code tensors",
                  described="named code tensors")


def read_trace(path: str | os.PathLike) -> dict[str, Any]:
    """A record written by `record`, checked for what `compare` reads (trace_files.read_record)."""
    return read_record(path, TRACE)


def compare(host: dict[str, Any], device: dict[str, Any]) -> dict[str, Any]:
    """Each code's first step apart (None: the same at every step both ran), and the codes
    that part first: where the two machines' arithmetic first differs."""
    if [c["name"] for c in host["codes"]] != [c["name"] for c in device["codes"]]:
        raise ValueError("the two traces are of different graphs (their code tensors differ)")
    apart = first_steps_apart(host, device, TRACE)
    return {"steps": apart["steps"], "codes": len(apart["items"]), "apart_by_end": apart["apart_by_end"],
            "first_step": apart["first_step"], "first_departures": apart["first_departures"],
            "per_code": apart["items"], "host_isa": host["isa"], "device_isa": device["isa"]}


def describe(code: dict[str, Any]) -> str:
    """`e3dpsm_code_11 (operator 412: ADD -> QUANTIZE -> FULLY_CONNECTED)`, with the tensor's
    name where the artifact kept litert-torch's (`convert litert --keep-tensor-names`)."""
    from e3dpsm.runtime.tflite_metadata import is_short_tensor_name

    name = code["tensor_name"]
    kept = "" if is_short_tensor_name(name) else f", {name.split(';')[0][-80:]}"
    return (f"{code['name']} (operator {code['operator']}: {code['fed_by']} -> QUANTIZE -> "
            f"{'/'.join(code['read_by']) or 'output'}{kept})")


def summary(report: dict[str, Any]) -> str:
    """One line: where the codes part first, or that they never do. Codes are in graph order,
    so the first of a step's departures is the most upstream: the rest may only follow it
    (or the float states, which are not codes, carried a difference into it)."""
    return departure_line(report, report["codes"], "code tensors", "in graph order", describe, "downstream at that step")


def main(argv: Sequence[str] | None = None) -> int:
    return trace_main(argv, TRACE, __doc__, record=record, compare=compare, summary=summary,
                      record_help="digests of every code tensor at every golden step, on this machine",
                      compare_help="where two machines' codes part (host first)")


if __name__ == "__main__":
    sys.exit(main())
