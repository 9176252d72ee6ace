"""runtime/stepping.py: the one place that picks an artifact's runner by its file extension
(docs/edge.md: .onnx ONNX Runtime, .pte ExecuTorch, .tflite LiteRT, .mlpackage Core ML,
.engine TensorRT), the one-line refusal of any other file (docs/bad-input.md), and what each
runner is opened with. The runners are replaced by recorders: no runtime is needed."""
from __future__ import annotations

import importlib

import pytest

from e3dpsm.errors import InputError
from e3dpsm.runtime.stepping import artifact_runtime, open_stepper

# docs/edge.md's table, with the module and class each runtime's runner lives in
DOCUMENTED = [(".onnx", "onnxruntime", "e3dpsm.runtime.session", "StepSession"),
              (".pte", "executorch", "e3dpsm.runtime.executorch_session", "ExecuTorchStepSession"),
              (".tflite", "litert", "e3dpsm.runtime.litert_session", "LiteRTStepSession"),
              (".mlpackage", "coreml", "e3dpsm.runtime.coreml_session", "CoreMLStepSession"),
              (".engine", "tensorrt", "e3dpsm.runtime.tensorrt_session", "TensorRTStepSession")]


@pytest.mark.parametrize("suffix, runtime, module, name", DOCUMENTED)
def test_each_extension_is_run_by_its_documented_runtime(suffix, runtime, module, name):
    """Any case, any folder (dots in it included); an artifact runner's own `runtime` agrees."""
    assert artifact_runtime(f"out.d/step{suffix}") == runtime
    assert artifact_runtime(f"STEP{suffix.upper()}") == runtime
    runner = getattr(importlib.import_module(module), name)
    if runtime != "onnxruntime":
        assert runner.runtime == runtime


@pytest.mark.parametrize("path, suffix", [("model.bin", "'.bin'"), ("a.onnx/model", "'(none)'"),
                                          ("model.onnx.gz", "'.gz'")])
def test_any_other_file_is_one_input_error_naming_the_known_types(path, suffix):
    """docs/bad-input.md: `...: unknown model file type '.bin'; expected one of .onnx, .pte,
    .tflite, .mlpackage, .engine`; a file without an extension says so."""
    expected = f"{path}: unknown model file type {suffix}; expected one of .onnx, .pte, .tflite, .mlpackage, .engine"
    for call in (artifact_runtime, open_stepper):
        with pytest.raises(InputError) as refused:
            call(path)
        assert str(refused.value) == expected


class Recorder:
    """Stands in for a runner class: remembers how it was opened."""

    opened: list = []

    def __init__(self, path, **kwargs):
        Recorder.opened.append((type(self).__name__, path, kwargs))


@pytest.mark.parametrize("suffix, runtime, module, name", DOCUMENTED)
def test_open_stepper_opens_the_runner_of_the_extension_with_threads(monkeypatch, suffix, runtime, module, name):
    """The runner of that extension's module, given the path and `threads`; the ONNX options
    (providers, spin...) reach StepSession alone, the other runners never see them."""
    monkeypatch.setattr(importlib.import_module(module), name, type(name, (Recorder,), {}))
    Recorder.opened = []
    path = f"out/step{suffix.upper()}"
    runner = open_stepper(path, threads=3, providers=["CPUExecutionProvider"])
    assert type(runner).__name__ == name
    options = {"threads": 3, "providers": ["CPUExecutionProvider"]} if runtime == "onnxruntime" else {"threads": 3}
    assert Recorder.opened == [(name, path, options)]
    open_stepper(path)
    assert Recorder.opened[-1] == (name, path, {"threads": None})
