"""Where an INT8 `.pte` parts between two machines without ExecuTorch's event tracer: its taps
program (`step_taps.pte`, written by `e3dpsm convert executorch --quantize int8 --taps`;
export/executorch_taps.py) returns the 8-bit codes of every quantised activation beside the
poses and states, and computes what `step.pte` computes. Each side steps it over the golden's
frames, its own states carried, and keeps an 8-byte digest of every tap at every step;
`compare` names the first step where a tap differs and the taps that part first, in program
order: the first of them reads only codes that agreed, so the float and integer arithmetic
between the taps before it and it (one quantised operator and the float ops in front of its
quantize) is where the machines part.

pte_trace.py traces every instruction's output but needs a runtime built with the event
tracer; this needs none, so it runs on PyPI's aarch64 ExecuTorch (and under emulation).

    python -m e3dpsm.golden.pte_taps record et8/step_taps.pte GOLDEN host.json [--steps N]
    python -m e3dpsm.golden.pte_taps record et8/step_taps.pte GOLDEN device.json  # on the device
    python -m e3dpsm.golden.pte_taps compare host.json device.json
"""
from __future__ import annotations

import os
import sys
from typing import Any, Sequence

import numpy as np

from e3dpsm.golden.trace_files import (TraceKind, departure_line, digest, first_steps_apart, read_record,
                                       trace_main)

TRACE = TraceKind(name="pte_taps", items="taps", key="tap", what="taps", described="taps")


def record(model: str | os.PathLike, golden_dir: str | os.PathLike, steps: int | None = None,
           threads: int | None = 1) -> dict[str, Any]:
    """Step the taps program `model` over the golden's frames (states carried by this runtime);
    every tap's digest at every step, and where this ran."""
    from e3dpsm.errors import InputError
    from e3dpsm.golden.store import load_golden
    from e3dpsm.runtime.executorch_session import ExecuTorchStepSession
    from e3dpsm.utils.isa import detect_isa

    if steps is not None and steps < 1:
        raise InputError(f"--steps {steps}: a trace needs at least one step")
    golden = load_golden(golden_dir)
    count = golden.steps if steps is None else min(steps, golden.steps)
    session = ExecuTorchStepSession(model, threads=threads)
    made = program_taps(session.program, str(model))
    if made is None:
        raise InputError(f"{model} has no taps: write its taps program with `e3dpsm convert executorch --quantize "
                         "int8 --taps` (step_taps.pte)")
    state = session.init_state(1)
    taps: list[dict[str, Any]] = []
    digests: list[list[str]] = []
    for step in range(count):
        _, state = session.step(golden.frame(step), state, golden.window_ms(step))
        values = session.extra_outputs  # the session binds the contract; the taps are the outputs past it
        if len(values) != len(made):
            raise ValueError(f"{model} returned {len(values)} values past its {len(session.output_names_all())} "
                             f"outputs, not its {len(made)} taps")
        if not taps:
            taps = [{**t, "shape": list(v.shape), "dtype": str(v.dtype)} for t, v in zip(made, values)]
        digests.append([digest(np.ascontiguousarray(v).tobytes()) for v in values])
    return {"model": str(model), "steps": count, "taps": taps, "digests": digests, "isa": detect_isa().to_dict()}


def program_taps(program: Any, source: str) -> list[dict[str, Any]] | None:
    """The taps (name and segment) a loaded ExecuTorch program carries (None: not a taps program)."""
    from e3dpsm.runtime.artifact_metadata import TAPS_METHOD, decode_taps

    if TAPS_METHOD not in program.method_names:
        return None
    return decode_taps(str(program.load_method(TAPS_METHOD).execute([])[0]), source)


def read_trace(path: str | os.PathLike) -> dict[str, Any]:
    """A record written by `record`, checked for what `compare` reads (trace_files.read_record)."""
    return read_record(path, TRACE)


def compare(host: dict[str, Any], device: dict[str, Any]) -> dict[str, Any]:
    """Each tap's first step apart (None: the same at every step both ran), and the taps that
    part first, in program order."""
    if [t["tap"] for t in host["taps"]] != [t["tap"] for t in device["taps"]]:
        raise ValueError("the two traces are of different programs (their taps differ)")
    apart = first_steps_apart(host, device, TRACE, position=True)
    return {"steps": apart["steps"], "taps": len(apart["items"]), "apart_by_end": apart["apart_by_end"],
            "first_step": apart["first_step"], "first_departures": apart["first_departures"],
            "per_tap": apart["items"], "host_isa": host["isa"], "device_isa": device["isa"]}


SEGMENT_SHOWN = 8  # a longer segment (a block kept float) is named by its distinct operators


def describe(tap: dict[str, Any]) -> str:
    """`model.stem.1:relu (tap 1, after conv2d, relu)`: the tap and the operators of its
    segment; a long one as `after 94 operators: view, div, ...`, each kind once, in order."""
    segment = tap["segment"]
    if not segment:
        return f"{tap['tap']} (tap {tap['position']}, a program input)"
    if len(segment) <= SEGMENT_SHOWN:
        return f"{tap['tap']} (tap {tap['position']}, after {', '.join(segment)})"
    return f"{tap['tap']} (tap {tap['position']}, after {len(segment)} operators: {', '.join(dict.fromkeys(segment))})"


def summary(report: dict[str, Any]) -> str:
    """One line: where the taps part first, or that they never do."""
    return departure_line(report, report["taps"], "taps", "in program order", describe, "at that step")


def main(argv: Sequence[str] | None = None) -> int:
    return trace_main(argv, TRACE, __doc__, record=record, compare=compare, summary=summary,
                      record_help="digests of every tap of a taps program at every golden step, on this machine",
                      compare_help="where two machines' taps part (host first)")


if __name__ == "__main__":
    sys.exit(main())
