"""The host's code trace of an INT8 `.tflite` or `.pte` kept in a golden folder, so that
`golden check` on a device that computes other poses than the host names where the two part,
as the kernel trace (kernel_report.py) does for an ONNX QDQ graph, with no second command.

`golden record --also ART --kernel-trace STEPS` records the host's half: for a `.tflite`
the digests of its 8-bit codes (tflite_trace.py), for a `.pte` those of its taps program's
(pte_taps.py: `step_taps.pte` beside it, from `convert executorch --quantize int8 --taps`,
copied into the golden since a device gets the golden folder and the shipped program only).
`golden check` of the same artifact, where its rollout is not the host's, records this
machine's half over the same steps and compares: check.json's `code_trace`, one line printed.

    GOLDEN/kernels/<stem>-<sha256[:12]>/host_trace.json   (and step_taps.pte for a .pte)
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path
from types import ModuleType
from typing import Any

HOST_FILE = "host_trace.json"
TAPS_PROGRAM = "step_taps.pte"


def trace_module(model: str | os.PathLike) -> ModuleType | None:
    """The trace that names where an artifact of this kind parts (None: not a .tflite or .pte)."""
    suffix = Path(model).suffix
    if suffix == ".tflite":
        from e3dpsm.golden import tflite_trace

        return tflite_trace
    if suffix == ".pte":
        from e3dpsm.golden import pte_taps

        return pte_taps
    return None


def record_host(golden_dir: str | os.PathLike, model: str | os.PathLike, steps: int,
                threads: int = 1) -> tuple[Path | None, str]:
    """The host's half, into the golden folder: (its folder, what it holds), or (None, why there is
    nothing to trace)."""
    from e3dpsm.golden.kernel_report import trace_folder
    from e3dpsm.golden.record import sha256_file
    from e3dpsm.utils.io import atomic_dir, write_json_atomic

    module = trace_module(model)
    if module is None:
        raise ValueError(f"{model}: an artifact trace is of a .tflite or a .pte")
    traced, program = Path(model), None
    if Path(model).suffix == ".pte":
        from e3dpsm.export.executorch_taps import taps_path

        traced = Path(taps_path(model))
        if not traced.is_file():
            return None, (f"no {traced.name} beside it to trace (write it with `e3dpsm convert executorch --quantize "
                          "int8 --taps`)")
        _check_taps_program(model, traced, golden_dir, steps, threads)
        program = TAPS_PROGRAM
    elif not _has_codes(model):
        return None, "no quantised activations (nothing is rounded at run time)"
    digest = sha256_file(model)
    folder = trace_folder(golden_dir, model, digest)
    with atomic_dir(folder, force=True) as tmp:
        if program:
            shutil.copyfile(traced, tmp / program)
        trace = module.record(tmp / program if program else traced, golden_dir, steps, threads)
        trace.update(model=Path(model).name, sha256=digest, trace=module.TRACE.name, program=program)
        write_json_atomic(tmp / HOST_FILE, trace)
    return folder, f"{trace['steps']} steps of {len(trace[module.TRACE.items])} {module.TRACE.what}"


def _check_taps_program(model: Path | str, taps: Path, golden_dir: str | os.PathLike, steps: int,
                        threads: int) -> None:
    """A taps program says where `model` parts only if it computes `model`'s steps: a stale one
    (from another conversion) is refused before anything is written."""
    from e3dpsm.errors import DataError
    from e3dpsm.export.executorch_taps import steps_identical
    from e3dpsm.golden.store import load_golden

    golden = load_golden(golden_dir)
    count = min(steps, golden.steps)
    same = steps_identical(model, taps, [golden.frame(s) for s in range(count)],
                           [golden.window_ms(s) for s in range(count)], threads)
    if same < count:
        raise DataError(f"{taps} does not compute {Path(model).name}'s steps (they differ from step {same}): write "
                        "both with one `e3dpsm convert executorch --quantize int8 --taps`")


def _has_codes(model: str | os.PathLike) -> bool:
    from e3dpsm.golden.tflite_trace import with_exposed_codes
    from e3dpsm.runtime.litert_session import read_tflite

    return bool(with_exposed_codes(read_tflite(model))[1])


def find_host_trace(golden_dir: str | os.PathLike, sha256: str | None) -> Path | None:
    """The folder of the golden's host trace of the artifact with this digest, if it keeps one."""
    from e3dpsm.golden.kernel_report import find_trace

    return find_trace(golden_dir, sha256, HOST_FILE)


def run_device(golden_dir: str | os.PathLike, model: str | os.PathLike, sha256: str | None,
               threads: int | None = 1) -> dict[str, Any] | None:
    """This machine's half over the host's steps, compared with the host's (the trace module's
    `compare`, its one line as `summary`); None where the golden keeps no trace of this artifact."""
    from e3dpsm.golden.trace_files import read_record

    module = trace_module(model)
    folder = None if module is None else find_host_trace(golden_dir, sha256)
    if folder is None:
        return None
    host = read_record(folder / HOST_FILE, module.TRACE)
    traced = folder / host["program"] if host.get("program") else Path(model)
    report = module.compare(host, module.record(traced, golden_dir, host["steps"], threads))
    return {"trace": module.TRACE.name, "summary": module.summary(report), **report}
