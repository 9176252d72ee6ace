"""The Core ML converter's own logic (export/coreml_export.py) without converting: the outputs
that alias another, the step without them, the package's size on disk, the refusals before
coremltools runs, and the Linux-side checks on a stand-in for a converted package (its
description and its ML program's constants), and what `convert_coreml` hands coremltools (a
stand-in module that records the call). The real conversion runs in the edge fixtures
(tests/_edge_helpers.py coreml_result)."""
from __future__ import annotations

import os
import time
import types

import numpy as np
import pytest
import torch

from _model_helpers import converter_tiny
from e3dpsm.errors import ConfigError
from e3dpsm.export import coreml_export
from e3dpsm.export.coreml_export import (PRECISIONS, WEIGHT_RTOL, CoreMLOptions, _DistinctOutputs, _package_bytes,
                                         check_package, convert_coreml, output_aliases, weights_in_package)
from e3dpsm.export.edge_export import NamedStepGraph

FLOAT32, FLOAT16 = 65568, 65552  # ArrayFeatureType.FLOAT32 / FLOAT16


@pytest.fixture(scope="module")
def model():
    return converter_tiny()


def test_an_output_that_is_the_same_tensor_as_an_earlier_one_is_an_alias(model) -> None:
    named = NamedStepGraph(model)
    with torch.no_grad():
        outputs = named(**named.example_kwargs())
    expected = {}
    for i, (name, value) in enumerate(outputs.items()):
        earlier = [n for n, v in list(outputs.items())[:i] if v is value]
        if earlier:
            expected[name] = earlier[0]
    assert output_aliases(named) == expected and expected  # the fused pose is also the fusion state
    distinct = _DistinctOutputs(named, set(expected))
    with torch.no_grad():
        kept = distinct(**named.example_kwargs())
    assert list(kept) == [n for n in named.spec.output_names if n not in expected]
    for name, value in kept.items():
        torch.testing.assert_close(value, outputs[name], rtol=0, atol=0)


def test_the_package_size_is_every_file_under_it(tmp_path) -> None:
    package = tmp_path / "step.mlpackage"
    (package / "Data" / "weights").mkdir(parents=True)
    (package / "Manifest.json").write_bytes(b"x" * 10)
    (package / "Data" / "model.mlmodel").write_bytes(b"x" * 200)
    (package / "Data" / "weights" / "weight.bin").write_bytes(b"x" * 3000)
    (package / "Data" / "empty").mkdir()
    assert _package_bytes(package) == 3210


@pytest.mark.parametrize("options, message", [
    (CoreMLOptions(precision="int8"), "unknown Core ML precision 'int8'; choose one of fp16, fp32"),
    (CoreMLOptions(attention_form="gather"),
     "Core ML takes the grid_sample attention form (the gather form's folded projections do not convert with "
     "coremltools 9); pass --attention-form grid_sample"),
])
def test_options_coremltools_cannot_take_are_refused_before_converting(model, tmp_path, monkeypatch, options,
                                                                     message) -> None:
    monkeypatch.setattr(coreml_export, "output_aliases", lambda *_: pytest.fail("converted"))
    monkeypatch.setattr(coreml_export, "require", lambda *_: types.SimpleNamespace())
    with pytest.raises(ConfigError) as error:
        convert_coreml(model, tmp_path / "step.mlpackage", options)
    assert str(error.value) == message and list(tmp_path.iterdir()) == []
    assert PRECISIONS == ("fp16", "fp32") and CoreMLOptions() == CoreMLOptions("grid_sample", "fp16")


def _op(op_type: str, value=None):
    return types.SimpleNamespace(op_type=op_type, outputs=[types.SimpleNamespace(val=value)])


def _feature(name, shape, dtype=FLOAT32):
    return types.SimpleNamespace(name=name, type=types.SimpleNamespace(
        multiArrayType=types.SimpleNamespace(shape=list(shape), dataType=dtype)))


def _weights(model):
    return [(n, m.weight.detach().numpy()) for n, m in model.named_modules()
            if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]


def test_weights_are_found_among_constants_of_their_shape_within_the_tolerance(model) -> None:
    weights = _weights(model)
    assert len(weights) > 3
    ops = [_op("const", w.copy()) for _, w in weights[2:]]
    name0, w0 = weights[0]
    scale = float(np.abs(w0).max())
    bump = np.zeros_like(w0)
    bump.flat[0] = 1.0
    ops.append(_op("const", w0 + 0.9e-3 * scale * bump))  # within fp16's tolerance
    name1, w1 = weights[1]
    ops.append(_op("const", w1 + 1.1e-3 * float(np.abs(w1).max()) * np.sign(w1 + 1e-9)))  # beyond it
    ops += [_op("const", None), _op("const", np.float32(1.0)), _op("conv", w1.copy()), _op("const", w1.reshape(-1))]
    result = weights_in_package(ops, model, WEIGHT_RTOL["fp16"])
    assert result == {"checked": len(weights), "found": len(weights) - 1, "missing": [name1]}
    strict = weights_in_package(ops, model, WEIGHT_RTOL["fp32"])
    assert strict["missing"] == [name0, name1]
    assert WEIGHT_RTOL == {"fp16": 1e-3, "fp32": 1e-6}
    assert weights_in_package([], model, 1e-3)["missing"] == [n for n, _ in weights]


def _package(spec, aliases, operations, input_dtype=FLOAT32, drop_output=None):
    outputs = [_feature(t.name, t.shape) for t in spec.outputs if t.name not in aliases and t.name != drop_output]
    description = types.SimpleNamespace(input=[_feature(t.name, t.shape, input_dtype) for t in spec.inputs],
                                        output=outputs)
    return types.SimpleNamespace(get_spec=lambda: types.SimpleNamespace(description=description),
                                 _mil_program=types.SimpleNamespace(functions={"main": types.SimpleNamespace(
                                     operations=operations)}))


def test_the_linux_side_checks_of_a_package(model) -> None:
    named = NamedStepGraph(model)
    aliases = output_aliases(named)
    spec = named.spec
    operations = [_op("conv"), _op("conv"), _op("add"), *(_op("const", w.copy()) for _, w in _weights(model))]
    checks = check_package(_package(spec, aliases, operations), model, spec, aliases, "fp32")
    want_in = {t.name: list(t.shape) for t in spec.inputs}
    want_out = {t.name: list(t.shape) for t in spec.outputs if t.name not in aliases}
    assert checks == {
        "inputs": {"expected": want_in, "found": want_in},
        "outputs": {"expected": want_out, "found": want_out, "aliases": aliases},
        "io_matches_spec": True, "float32_io": True,
        "operators": {"const": len(_weights(model)), "conv": 2, "add": 1},
        "weights": {"checked": len(_weights(model)), "found": len(_weights(model)), "missing": []},
        "passed": True,
    }
    half = check_package(_package(spec, aliases, operations, input_dtype=FLOAT16), model, spec, aliases, "fp16")
    assert half["float32_io"] is False and half["io_matches_spec"] is True and half["passed"] is False
    dropped = next(iter(want_out))
    short = check_package(_package(spec, aliases, operations, drop_output=dropped), model, spec, aliases, "fp16")
    assert short["io_matches_spec"] is False and short["passed"] is False and dropped not in short["outputs"]["found"]


def test_a_missing_extra_and_the_form_coremltools_takes(model, tmp_path, monkeypatch) -> None:
    import dataclasses
    import sys

    class Reached(Exception):
        pass

    def reached(*_):
        raise Reached

    monkeypatch.setattr(coreml_export, "output_aliases", reached)
    monkeypatch.setitem(sys.modules, "coremltools", types.ModuleType("coremltools"))
    with pytest.raises(Reached):  # grid_sample and fp32 pass the checks: the conversion starts
        convert_coreml(model, tmp_path / "step.mlpackage", CoreMLOptions(precision="fp32"))
    monkeypatch.setitem(sys.modules, "coremltools", None)
    with pytest.raises(ConfigError) as error:
        convert_coreml(model, tmp_path / "step.mlpackage")
    assert str(error.value) == 'coremltools is not installed (to write .mlpackage programs): pip install -e ".[coreml]"'
    with pytest.raises(dataclasses.FrozenInstanceError):
        CoreMLOptions().precision = "fp32"
    bare = coreml_export.CoreMLResult(path="p", bytes=1, seconds={}, checks={}, options={})
    assert bare.to_dict() == {"path": "p", "bytes": 1, "seconds": {}, "checks": {}, "options": {}, "artifact": {}}
    assert coreml_export.FORMAT == "coreml"


class _FakeCoremltools(types.ModuleType):
    """coremltools' surface that convert_coreml touches, recording the conversion it is asked
    for; its package writes a 10-byte file when saved."""

    def __init__(self) -> None:
        super().__init__("coremltools")
        self.precision = types.SimpleNamespace(FLOAT16="float16 compute", FLOAT32="float32 compute")
        self.target = types.SimpleNamespace(iOS17="iOS17")
        self.converted: dict = {}

    @staticmethod
    def TensorType(name, dtype):  # noqa: N802 (coremltools' name)
        return (name, dtype)

    def convert(self, program, **kwargs):
        self.converted = {"program": program, **kwargs}
        time.sleep(0.0123)

        class Package:
            user_defined_metadata: dict = {}

            def save(self, path):
                os.makedirs(path)
                with open(os.path.join(path, "weight.bin"), "wb") as f:
                    f.write(b"0123456789")

        return Package()


@pytest.mark.parametrize("precision", PRECISIONS)
def test_convert_coreml_hands_coremltools_the_exported_step_without_aliases(model, tmp_path, monkeypatch,
                                                                            precision) -> None:
    import sys

    from e3dpsm.runtime.artifact_metadata import EMBEDDED_NAME, decode

    fake = _FakeCoremltools()
    monkeypatch.setitem(sys.modules, "coremltools", fake)
    checked = []
    monkeypatch.setattr(coreml_export, "check_package",
                        lambda package, m, spec, aliases, p: checked.append((package, m, aliases, p)) or {"passed": 1})
    path = tmp_path / "step.mlpackage"
    result = convert_coreml(model, path, CoreMLOptions(precision=precision))

    named = NamedStepGraph(model).eval()
    names = [n for n in named.spec.output_names if n != "fusion_pose_out"]
    converted = fake.converted
    assert converted.pop("outputs") == [(n, np.float32) for n in names]
    assert converted.pop("convert_to") == "mlprogram" and converted.pop("minimum_deployment_target") == "iOS17"
    assert converted.pop("compute_precision") == f"float{precision[2:]} compute"
    program = converted.pop("program")
    assert converted == {}
    # the exported program computes the step without the alias
    kwargs = named.example_kwargs()
    with torch.no_grad():
        want = named(**kwargs)
    got = program.module()(**kwargs)
    assert list(got) == names
    for name in names:
        torch.testing.assert_close(got[name], want[name], rtol=0, atol=1e-5)

    package, checked_model, aliases, checked_precision = checked[0]
    assert (checked_model, aliases, checked_precision) == (model, {"fusion_pose_out": "pose"}, precision)
    meta, record = decode(package.user_defined_metadata[EMBEDDED_NAME], "package")
    assert record == result.artifact and record["precision"] == precision and record["format"] == "coreml"
    assert record["output_aliases"] == {"fusion_pose_out": "pose"} and meta.config["format"] == "coreml"
    assert set(record["versions"]) == {"torch", "coremltools"} and all(record["versions"].values())
    assert result.path == str(path) and result.bytes == 10 and result.checks == {"passed": 1}
    assert result.options == {"attention_form": "grid_sample", "precision": precision}
    seconds = result.seconds
    assert list(seconds) == ["convert", "save", "total"] and all(v == round(v, 2) for v in seconds.values())
    assert 0.01 <= seconds["convert"] <= seconds["total"] < 300 and 0 <= seconds["save"] <= seconds["total"]
