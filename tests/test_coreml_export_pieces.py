"""The Core ML converter's own logic (export/coreml_export.py) without converting: the outputs
that alias another, the step without them, the package's size on disk, the refusals before
coremltools runs, and the Linux-side checks on a stand-in for a converted package (its
description and its ML program's constants). The conversion itself runs in the edge fixtures
(tests/_edge_helpers.py coreml_result)."""
from __future__ import annotations

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
