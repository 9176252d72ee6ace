"""The taps of an INT8 `.pte` (export/executorch_taps.py) where they are made: on a PT2E-converted
toy (tests/_toy_pt2e.py), which quantize ops are taps and what a tapped module returns (its
outputs unchanged, then codes checked against numpy's rounding of the same activation); how
convert_executorch hands the tap names to ExecuTorch; and convert_executorch_int8's taps
program: the same quantizer and calibration, checked against the shipped program or refused.
The taps read back on a device: tests/test_pte_taps_pieces.py."""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch

pytest.importorskip("executorch", reason="executorch (pip extra executorch) is not installed")

from _model_helpers import converter_tiny  # noqa: E402
from _toy_pt2e import ToyRecurrent, toy_program  # noqa: E402
from e3dpsm.export import executorch_export, executorch_int8  # noqa: E402
from e3dpsm.export.executorch_int8 import calibrator, xnnpack_int8_quantizer  # noqa: E402
from e3dpsm.export.executorch_taps import activation_quantizes, tap_name, tap_segment, with_taps  # noqa: E402



def _quantize():
    import torchao.quantization.pt2e.quantize_pt2e  # noqa: F401 registers quantized_decomposed

    return torch.ops.quantized_decomposed.quantize_per_tensor.default


@pytest.fixture()
def converted(monkeypatch) -> tuple[torch.fx.GraphModule, tuple[torch.Tensor]]:
    program, example = toy_program()
    monkeypatch.setattr(executorch_int8, "KEEP_FLOAT_TYPES", (ToyRecurrent,))
    module = executorch_export.quantized_module(program, xnnpack_int8_quantizer(),
                                                calibrator([example, (2 * example[0],)]))
    return module, example


def test_a_tapped_module_returns_its_outputs_then_every_activations_codes(converted) -> None:
    module, example = converted
    with torch.no_grad():
        want = module(*example)
    quantizes = activation_quantizes(module.graph)
    first_scale, first_zero = quantizes[0].args[1:3]
    tapped, taps = with_taps(module)
    names = [t["tap"] for t in taps]
    assert names == [":x", "model.stem:conv2d", "model.stages.0:conv2d_1", "model.stages.1:conv2d_2", "model:mean",
                     "model.ssm.proj:linear", "model.ssm.rec.lin:linear_1", "model.decoder:linear_2"]
    # each segment: the operators from the codes (or parameters) it reads to its quantize
    assert [t["segment"] for t in taps] == [[], ["conv2d"], ["conv2d"], ["conv2d"], ["mean"], ["linear"],
                                            ["linear"], ["linear"]]
    with torch.no_grad():
        got = tapped(*example)
    assert len(got) == len(want) + len(names)
    assert all(torch.equal(a, b) for a, b in zip(got, want))  # the step's own outputs, unchanged
    assert all(t.dtype == torch.int8 for t in got[len(want):])
    # the input's codes, from numpy: round half to even, then the zero point, saturated
    codes = np.clip(np.round(example[0].numpy() / np.float32(first_scale)) + first_zero, -128, 127).astype(np.int8)
    np.testing.assert_array_equal(got[len(want)].numpy(), codes)
    assert len(np.unique(codes)) > 20  # codes spread over the range: a wrong scale would not match


def test_weights_are_no_taps_and_a_module_without_activations_is_refused(converted) -> None:
    quantize = _quantize()
    graph = torch.fx.Graph()
    x = graph.placeholder("x")
    weight = graph.get_attr("w")
    quantized = [graph.call_function(quantize, (v, 0.1, 0, -128, 127, torch.int8)) for v in (x, weight)]
    graph.output((quantized[0], quantized[1]))
    assert activation_quantizes(graph) == [quantized[0]]
    assert tap_name(quantized[0]) == ":x" and tap_segment(quantized[0]) == []
    root = torch.nn.Module()
    root.register_buffer("w", torch.ones(2))
    with pytest.raises(ValueError, match="^the module has no quantised activation to tap: tap a PT2E-converted "
                                         "INT8 module$"):
        with_taps(torch.fx.GraphModule(root, torch.fx.symbolic_trace(lambda x: (x + 1, x)).graph))
    single = torch.fx.Graph()
    y = single.placeholder("y")
    single.output(single.call_function(quantize, (y, 0.1, 0, -128, 127, torch.int8)))
    with pytest.raises(ValueError, match="^the module returns one value, not the step wrapper's tuple of poses and "
                                         "states$"):
        with_taps(torch.fx.GraphModule(torch.nn.Module(), single))


class _Lowering:
    """convert_executorch's ExecuTorch calls, answered without lowering: the transform it passes
    is applied to the converted toy."""

    def __init__(self, module: torch.fx.GraphModule) -> None:
        self.module, self.methods = module, None

    def export_step_program(self, model, options, quantizer, calibrate, transform):
        self.tapped = transform(self.module) if transform else None
        return "PROGRAM"

    def to_edge(self, program, partitioner, constant_methods):
        self.methods = dict(constant_methods)
        return types.SimpleNamespace(to_executorch=lambda: types.SimpleNamespace(buffer=b"PTE"))


def test_convert_writes_the_tap_names_into_the_program(converted, tmp_path, monkeypatch) -> None:
    import executorch.exir

    from e3dpsm.export import delegation
    from e3dpsm.runtime.artifact_metadata import PTE_METHOD, TAPS_METHOD, decode_taps

    lowering = _Lowering(converted[0])
    monkeypatch.setattr(executorch_export, "export_step_program", lowering.export_step_program)
    monkeypatch.setattr(executorch.exir, "to_edge_transform_and_lower", lowering.to_edge)
    monkeypatch.setattr(delegation, "delegation_summary", lambda edge: {})
    monkeypatch.setattr(executorch_int8, "int8_coverage", lambda edge: {})
    model = converter_tiny()
    result = executorch_export.convert_executorch(model, tmp_path / "t.pte", precision="int8", quantizer=object(),
                                                  calibrate=None, taps=True)
    assert set(lowering.methods) == {PTE_METHOD, TAPS_METHOD}
    taps = decode_taps(lowering.methods[TAPS_METHOD], "t")
    assert len(taps) == 8 and taps[1] == {"tap": "model.stem:conv2d", "segment": ["conv2d"]}
    assert result.taps == {"count": 8}
    assert result.to_dict()["taps"] == {"count": 8}
    plain = executorch_export.convert_executorch(model, tmp_path / "p.pte", precision="int8", quantizer=object(),
                                                 calibrate=None)
    assert lowering.tapped is None and set(lowering.methods) == {PTE_METHOD}
    assert plain.taps == {} and "taps" not in plain.to_dict()
    with pytest.raises(ValueError, match="an fp32 program has none"):
        executorch_export.convert_executorch(model, tmp_path / "f.pte", taps=True)
    assert not (tmp_path / "f.pte").exists()


@pytest.mark.parametrize("identical", [True, False])
def test_the_taps_program_is_the_shipped_ones_calibration_checked_step_by_step(tmp_path, monkeypatch,
                                                                               identical) -> None:
    from e3dpsm.export import executorch_taps

    calls = []

    def convert(model, path, program, precision, quantizer, calibrate, extra_record, taps):
        calls.append((path, program, precision, quantizer, calibrate, extra_record, taps))
        return types.SimpleNamespace(bytes=123, taps={"count": 9}, seconds={"total": 4.5})

    def same(shipped, tapped, frames, windows, threads):
        calls.append((shipped, tapped, [f[0, 0, 0, 0] for f in frames], windows, threads))
        return len(frames) if identical else 3

    monkeypatch.setattr(executorch_export, "convert_executorch", convert)
    monkeypatch.setattr(executorch_taps, "steps_identical", same)
    monkeypatch.setattr(executorch_int8, "xnnpack_int8_quantizer", lambda keep: ("quantizer", tuple(keep)))
    model = converter_tiny()
    feeds = [{"lnes": np.full((1, 2, 32, 64), k, np.float32), "window_ms": np.array([10.0 + k], np.float32)}
             for k in range(40)]
    calibration = types.SimpleNamespace(feeds=feeds)
    path = tmp_path / "step.pte"
    args = (model, path, "PROGRAM", ["model.stem"], "CALIBRATE", {"budget": 1}, calibration, 2)
    if not identical:
        from e3dpsm.export.onnx_export import ExportError

        with pytest.raises(ExportError, match=r"step_taps\.pte parts from step\.pte at step 3 on this host"):
            executorch_int8.write_taps_program(*args)
        return
    assert executorch_int8.write_taps_program(*args) == {"file": "step_taps.pte", "bytes": 123, "taps": 9,
                                                         "identical_steps": 32, "seconds": 4.5}
    (twin, program, precision, quantizer, calibrate, record, taps), checked = calls
    assert (twin, program, precision, quantizer, calibrate, taps) == (
        str(tmp_path / "step_taps.pte"), "PROGRAM", "int8", ("quantizer", ("model.stem",)), "CALIBRATE", True)
    assert record == {"budget": 1, "taps_of": "step.pte"}
    assert checked == (path, str(tmp_path / "step_taps.pte"), list(range(32)), [10.0 + k for k in range(32)], 2)
    assert executorch_int8.TAPS_CHECK_STEPS == 32


def test_a_segment_runs_back_through_every_branch_to_codes_inputs_and_constants() -> None:
    """q(relu(add(mul(dq(q(x)), 2), y)) + w): the walk stops at the dequantize, the input y and
    the constant w on each branch, and keeps going past each of them on the others."""
    import torchao.quantization.pt2e.quantize_pt2e  # noqa: F401 registers quantized_decomposed

    aten, ops = torch.ops.aten, torch.ops.quantized_decomposed
    graph = torch.fx.Graph()
    x, y, w = graph.placeholder("x"), graph.placeholder("y"), graph.get_attr("w")
    codes = graph.call_function(ops.quantize_per_tensor.default, (x, 0.1, 0, -128, 127, torch.int8))
    values = graph.call_function(ops.dequantize_per_tensor.default, (codes, 0.1, 0, -128, 127, torch.int8))
    scaled = graph.call_function(aten.mul.Tensor, (values, 2.0))
    summed = graph.call_function(aten.add.Tensor, (y, scaled))
    shifted = graph.call_function(aten.add.Tensor, (graph.call_function(aten.relu.default, (summed,)), w))
    tap = graph.call_function(ops.quantize_per_tensor.default, (shifted, 0.1, 0, -128, 127, torch.int8))
    graph.output((tap,))
    assert activation_quantizes(graph) == [codes, tap]
    assert tap_segment(tap) == ["mul", "add", "relu", "add"] and tap_segment(codes) == []
