"""The ExecuTorch converter's own work (export/executorch_export.py): the norms decomposed for
XNNPACK, the parameter-only subgraphs folded (quantize / dequantize left alone in a quantised
program), and convert_executorch's orchestration with the lowering recorded (what it hands
ExecuTorch, what it writes and reports). A real lowering of the tiny runs in the edge
fixtures (tests/_edge_helpers.py pte_path) and test_executorch_session_pieces.py steps a
.pte written by ExecuTorch's own API."""
from __future__ import annotations

import types

import pytest
import torch

pytest.importorskip("executorch", reason="executorch (pip extra executorch) is not installed")

from _model_helpers import converter_tiny  # noqa: E402
from _io_helpers import record_temporaries  # noqa: E402
from e3dpsm.export import delegation, executorch_export  # noqa: E402
from e3dpsm.export.edge_export import artifact_contract  # noqa: E402
from e3dpsm.export.executorch_export import (ExecuTorchOptions, convert_executorch,  # noqa: E402
                                             export_step_program, fold_skip_targets, step_program)
from e3dpsm.runtime.artifact_metadata import PTE_METHOD, decode  # noqa: E402

NORMS = {"aten.layer_norm.default", "aten.group_norm.default"}


@pytest.fixture(scope="module")
def model():
    return converter_tiny()


def _targets(program) -> set[str]:
    return {str(n.target) for n in program.graph.nodes if n.op == "call_function"}


def test_the_norms_go_in_as_matmuls_unless_asked_not_to(model) -> None:
    kept = step_program(model, ExecuTorchOptions(decompose_norms=False))
    assert NORMS <= _targets(kept)
    decomposed = step_program(model, ExecuTorchOptions())
    assert not NORMS & _targets(decomposed)
    example = executorch_export.StepGraph(model).example_inputs(1)
    with torch.no_grad():
        for a, b in zip(kept.module()(*example), decomposed.module()(*example)):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


def test_parameter_only_subgraphs_are_folded_when_asked(model) -> None:
    options = ExecuTorchOptions(decompose_norms=False, fold_constants=False)
    plain = export_step_program(model, options)
    folded = export_step_program(model, ExecuTorchOptions(decompose_norms=False))
    count = lambda p: sum(1 for n in p.graph.nodes if n.op == "call_function")  # noqa: E731
    assert count(folded) < count(plain)
    assert len(folded.constants) + len(folded.state_dict) > 0
    example = executorch_export.StepGraph(model).example_inputs(1)
    with torch.no_grad():
        for a, b in zip(plain.module()(*example), folded.module()(*example)):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_a_quantised_program_keeps_its_quantize_and_dequantize_ops() -> None:
    from executorch.exir.passes.constant_prop_pass import get_default_skip_targets_no_quant

    assert fold_skip_targets(False) is None
    skipped = fold_skip_targets(True)
    assert set(get_default_skip_targets_no_quant()) <= skipped
    ops = torch.ops.quantized_decomposed
    for name in ("quantize_per_tensor", "dequantize_per_tensor", "quantize_per_channel", "dequantize_per_channel"):
        packet = getattr(ops, name)
        assert {getattr(packet, overload) for overload in packet.overloads()} <= skipped, name
        assert packet.overloads()
    assert len(skipped) == len(set(get_default_skip_targets_no_quant())) + sum(
        len(getattr(ops, n).overloads()) for n in ("quantize_per_tensor", "dequantize_per_tensor",
                                                     "quantize_per_channel", "dequantize_per_channel"))


class Lowering:
    """Records what convert_executorch hands ExecuTorch, and answers like it."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def export_step_program(self, model, options, quantizer, calibrate, transform):
        self.calls.append(("export", model.training, options, quantizer, calibrate, transform,
                           [p.requires_grad for p in model.parameters()][:1]))
        return "PROGRAM"

    def to_edge(self, program, partitioner, constant_methods):
        self.calls.append(("lower", program, [type(p).__name__ for p in partitioner], dict(constant_methods)))
        return types.SimpleNamespace(to_executorch=lambda: types.SimpleNamespace(buffer=b"PTE-BYTES"))


@pytest.mark.parametrize("quantized", [False, True])
def test_convert_hands_executorch_the_program_and_the_contract_and_writes_what_it_gets(model, tmp_path, monkeypatch,
                                                                                       quantized) -> None:
    import executorch.exir

    from e3dpsm.export import executorch_int8

    lowering = Lowering()
    temporaries = record_temporaries(monkeypatch, executorch_export)
    clock = iter([1.0, 2.1234, 3.4567, 4.0])  # started, exported, lowered, written
    monkeypatch.setattr(executorch_export.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(executorch_export, "export_step_program", lowering.export_step_program)
    monkeypatch.setattr(executorch.exir, "to_edge_transform_and_lower", lowering.to_edge)
    monkeypatch.setattr(delegation, "delegation_summary", lambda edge: {"delegated_share": 0.9})
    monkeypatch.setattr(executorch_int8, "int8_coverage", lambda edge: {"int8_share": 0.7})
    model.train()
    options = ExecuTorchOptions(attention_form="gather", decompose_norms=False)
    quantizer, calibrate = (object(), lambda m: None) if quantized else (None, None)
    path = tmp_path / "out" / "step.pte"
    given = {"precision": "int8", "quantizer": quantizer, "calibrate": calibrate} if quantized else {}
    result = convert_executorch(model, path, options, **given, extra_record={"budget": {"limit_pct": 1.0}})
    (_, training, given_options, given_quantizer, given_calibrate, transform, grads), lower = lowering.calls
    assert training is False and grads == [False] and transform is None  # exported from the frozen eval model
    assert (given_options, given_quantizer, given_calibrate) == (options, quantizer, calibrate)
    assert model.training  # given back
    assert lower[:3] == ("lower", "PROGRAM", ["XnnpackPartitioner"])
    assert list(lower[3]) == [PTE_METHOD]  # no taps method unless asked
    meta, record = decode(lower[3][PTE_METHOD], "x")
    expected_meta, expected_record = artifact_contract(
        model, "executorch", "int8" if quantized else "fp32", "gather", ("executorch",),
        {"decompose_norms": False, "budget": {"limit_pct": 1.0}})
    assert meta.to_props() == expected_meta.to_props() and record == expected_record == result.artifact
    assert path.read_bytes() == b"PTE-BYTES" and result.bytes == 9 and result.path == str(path)
    assert [p.name for p in path.parent.iterdir()] == ["step.pte"]
    assert result.delegation == ({"delegated_share": 0.9, "int8": {"int8_share": 0.7}} if quantized
                                 else {"delegated_share": 0.9})
    assert result.options == {"attention_form": "gather", "decompose_norms": False, "fold_constants": True}
    assert result.seconds == {"export": 1.12, "lower": 1.33, "serialize": 0.54, "total": 3.0}
    assert len(temporaries) == 1 and temporaries[0].startswith(".step.pte.") and temporaries[0].endswith(".pte")
    assert result.to_dict()["delegation"] == result.delegation
    model.eval()


def test_the_options_defaults_and_the_results_record() -> None:
    import dataclasses

    assert ExecuTorchOptions() == ExecuTorchOptions("grid_sample", True, True)
    with pytest.raises(dataclasses.FrozenInstanceError):
        ExecuTorchOptions().attention_form = "gather"
    bare = executorch_export.ExecuTorchResult(path="p", bytes=1, seconds={}, delegation={}, options={})
    assert bare.to_dict()["artifact"] == {}


def test_without_the_extra_nothing_is_written_and_the_line_names_it(model, tmp_path, monkeypatch) -> None:
    from e3dpsm.errors import ConfigError

    monkeypatch.setitem(__import__("sys").modules, "executorch", None)
    path = tmp_path / "step.pte"
    with pytest.raises(ConfigError, match=r'^executorch is not installed \(to write .pte programs\): '
                                          r'pip install -e "\.\[executorch\]"$'):
        convert_executorch(model, path)
    assert not path.exists()
