"""The one stepping protocol: `init_state(batch)` and `step(lnes, state, window_ms) ->
(outputs, state)`, numpy in and numpy out, the caller carrying the states.

Every consumer that steps a model frame by frame (parity, golden record and check,
diagnose, the latency timers) is written against this protocol, so an ONNX Runtime
session, an OpenVINO session and the PyTorch model (`e3dpsm.export.torch_stepper`, kept
beside the exporter because it needs torch) are interchangeable there. Torch-free.

`open_stepper(path)` is the one place that picks the runner of an artifact by its file
extension: every consumer (golden check, run, serve, validate, profile) opens files here.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Protocol

import numpy as np

from e3dpsm.graph_metadata import GraphMetadata

StateArrays = dict[str, np.ndarray]


class Stepper(Protocol):
    """A model stepped one frame at a time: `lnes` is float32 [B, 2, H, W], `state` the dict
    `init_state` returned (or the previous step did), keyed by state name."""

    def init_state(self, batch: int = 1) -> StateArrays: ...

    def step(self, lnes: np.ndarray, state: Mapping[str, np.ndarray],
             window_ms: float) -> tuple[dict[str, np.ndarray], StateArrays]: ...


class GraphStepper(Stepper, Protocol):
    """A stepper over an exported graph: what checks against the graph's own contract (its
    metadata and input / output names) need on top of stepping."""

    meta: GraphMetadata

    def input_names(self) -> list[str]: ...

    def output_names_all(self) -> list[str]: ...


class StreamStepper(GraphStepper, Protocol):
    """What the stream runtimes (runtime/stream.py, multistream.py, serve) use on top: the
    file, and feeds checked apart from the run (so they time the runtime alone)."""

    path: Path

    def feeds(self, lnes: np.ndarray, state: Mapping[str, np.ndarray],
              window_ms: float | np.ndarray) -> dict[str, np.ndarray]: ...

    def run_feeds(self, feeds: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], StateArrays]: ...



# extension -> (runtime name, module, class); the module is imported only when used, so a
# device with one runtime installed never imports the others.
ARTIFACT_RUNNERS: dict[str, tuple[str, str, str]] = {
    ".onnx": ("onnxruntime", "e3dpsm.runtime.session", "StepSession"),
    ".pte": ("executorch", "e3dpsm.runtime.executorch_session", "ExecuTorchStepSession"),
    ".tflite": ("litert", "e3dpsm.runtime.litert_session", "LiteRTStepSession"),
    ".mlpackage": ("coreml", "e3dpsm.runtime.coreml_session", "CoreMLStepSession"),
    ".engine": ("tensorrt", "e3dpsm.runtime.tensorrt_session", "TensorRTStepSession"),
}


def artifact_runtime(path: str | os.PathLike) -> str:
    """The runtime that runs `path`, by its extension (InputError for an unknown one)."""
    from e3dpsm.errors import InputError

    suffix = Path(path).suffix.lower()
    if suffix not in ARTIFACT_RUNNERS:
        raise InputError(f"{path}: unknown model file type {suffix or '(none)'!r}; expected one of "
                         f"{', '.join(ARTIFACT_RUNNERS)}")
    return ARTIFACT_RUNNERS[suffix][0]


def open_stepper(path: str | os.PathLike, *, threads: int | None = None, **onnx_options: Any) -> StreamStepper:
    """The `GraphStepper` of a step artifact, chosen by its extension: .onnx (ONNX Runtime;
    `onnx_options` such as providers, options, spin go to `StepSession`), .pte (ExecuTorch),
    .tflite (LiteRT), .mlpackage (Core ML, macOS), .engine (TensorRT, NVIDIA GPU)."""
    import importlib

    runtime = artifact_runtime(path)
    _, module, name = ARTIFACT_RUNNERS[Path(path).suffix.lower()]
    runner = getattr(importlib.import_module(module), name)
    if runtime == "onnxruntime":
        return runner(path, threads=threads, **onnx_options)
    return runner(path, threads=threads)
