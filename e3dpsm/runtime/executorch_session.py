"""Drive an ExecuTorch step program (`.pte`, `e3dpsm convert executorch`) with ExecuTorch's
Python runtime (XNNPACK and portable kernels). Extra: `pip install -e ".[executorch]"`; the
runtime's Python binding takes torch tensors, so this runner imports torch (a device app
links the C++ runtime instead).

The state layout is the program's own constant method `e3dpsm_metadata`
(runtime/artifact_metadata.py), with the input and output order it was written in and the
ExecuTorch version that wrote it: a program from another release is refused before it runs
(unless OTHER_RELEASE_ENV says to run it anyway)."""
from __future__ import annotations

import contextlib
import importlib.metadata
import os
import sys
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from e3dpsm.errors import DataError
from e3dpsm.graph_metadata import MetadataError
from e3dpsm.runtime.artifact_metadata import PTE_METHOD, decode
from e3dpsm.runtime.artifact_session import ArtifactSession
from e3dpsm.utils.extras import require

FORMAT = "executorch"
# "1": run a program written by another ExecuTorch release instead of refusing it. For checks
# across releases only, e.g. benchmarks/arm_emulation.py, whose aarch64 root has the newest
# runtime PyPI pairs with a CPU build of torch for aarch64, not the release that wrote the program.
OTHER_RELEASE_ENV = "E3DPSM_EXECUTORCH_OTHER_RELEASE"
PTE_IDENTIFIER_AT = slice(4, 8)  # the flatbuffer file identifier ("ET12" for ExecuTorch 1.x)


def executorch_version() -> str:
    return importlib.metadata.version("executorch")


def same_release(a: str, b: str) -> bool:
    """Same major.minor: ExecuTorch does not promise to run programs of other releases."""
    return a.split(".")[:2] == b.split(".")[:2]


@contextlib.contextmanager
def native_log_silenced():
    """The runtime's log (cpuinfo probes, a refused program's identifier) goes to the
    process's stderr, from C++ and through Python's sys.stderr; while loading, it goes
    nowhere, so a refusal is the one error line of the CLI."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null, contextlib.redirect_stderr(null):
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def load_program(path: str | os.PathLike) -> Any:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"model {path} does not exist")
    runtime = require("executorch.runtime", "to run .pte programs")  # a missing extra is its own error
    try:
        with native_log_silenced():
            return runtime.Runtime.get().load_program(path)
    except Exception as exc:  # the binding raises RuntimeError / ValueError for unreadable programs
        head = path.read_bytes()[:8]
        raise DataError(f"ExecuTorch {executorch_version()} cannot load {path} (file identifier "
                        f"{head[PTE_IDENTIFIER_AT]!r}): written by another ExecuTorch version or not a .pte; "
                        "convert it again with this one") from exc


def program_metadata(path: str | os.PathLike, program: Any):
    """(GraphMetadata, artifact record) from the program's `e3dpsm_metadata` method."""
    if PTE_METHOD not in program.method_names:
        raise MetadataError(f"{path} carries no e3dpsm state layout (no {PTE_METHOD} method); "
                            "write it with `e3dpsm convert executorch`")
    meta, artifact = decode(program.load_method(PTE_METHOD).execute([])[0], str(path))
    written_by = str(artifact.get("versions", {}).get("executorch"))
    if not same_release(written_by, executorch_version()) and os.environ.get(OTHER_RELEASE_ENV) != "1":
        raise DataError(f"{path} was written by ExecuTorch {written_by}, this runtime is {executorch_version()}; "
                        f"convert it again here, or run it with executorch=={written_by}")
    return meta, artifact


class ExecuTorchStepSession(ArtifactSession):
    runtime = FORMAT

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None) -> None:
        import torch

        self._torch = torch
        program = load_program(path)
        meta, self.artifact = program_metadata(path, program)
        with native_log_silenced():  # XNNPACK probes the CPU (cpuinfo) when it first starts
            if self.artifact.get("precision") == "int8":
                import executorch.kernels.quantized  # noqa: F401  (kernels of Q/DQ left outside XNNPACK)
            if threads:
                from executorch.extension.pybindings import portable_lib

                portable_lib._unsafe_reset_threadpool(int(threads))  # XNNPACK's pool is per process
            self._method = program.load_method("forward")
        self._program = program  # the method runs on the program's buffers: both live as long as the session
        # What the program's last call (one batch row) returned past the contract's outputs: a
        # taps program's 8-bit codes (golden/pte_taps.py); empty for a step program. The runtime
        # returns new tensors at every call, so what a step left here outlives the next step.
        self.extra_outputs: tuple[np.ndarray, ...] = ()
        self._bind(path, meta, list(self.artifact.get("inputs", [])), list(self.artifact.get("outputs", [])))

    @property
    def program(self) -> Any:
        """The loaded ExecuTorch program, for its other methods (`e3dpsm_taps`)."""
        return self._program

    def use_method(self, method: Any) -> None:
        """Step through `method` from now on: any object with `execute(list of tensors) -> list
        of tensors` computing this program's forward (the same program loaded with ETDump on:
        golden/pte_trace.py). Inputs, outputs and states stay this session's contract."""
        if not callable(getattr(method, "execute", None)):
            raise TypeError(f"{type(method).__name__} has no execute(inputs): not an ExecuTorch method")
        self._method = method

    def _run_one(self, feeds: Mapping[str, np.ndarray]) -> dict[str, Any]:
        values = list(self._method.execute([self._torch.from_numpy(np.ascontiguousarray(feeds[n]))
                                            for n in self._inputs]))
        if len(values) < len(self._outputs):
            raise DataError(f"{self.path} returned {len(values)} values, fewer than its {len(self._outputs)} outputs")
        self.extra_outputs = tuple(v.numpy() for v in values[len(self._outputs):])
        return {name: value.numpy() for name, value in zip(self._outputs, values)}
