"""The export side's three small adapters, each against the thing it adapts: the positional
step module exporters trace (export/wrapper.py) and the numpy stepper of the PyTorch model
(export/torch_stepper.py) against `model.step`, and ONNX Runtime's pre-optimised copy
(export/ort_optimized.py) against the rewrites each optimisation level is documented to make."""
from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper

import e3dpsm
from _io_helpers import record_temporaries
from e3dpsm.errors import ConfigError
from e3dpsm.export.ort_optimized import ORT_LEVELS, write_ort_optimized
from e3dpsm.export.torch_stepper import TorchStepper
from e3dpsm.export.wrapper import StepGraph
from e3dpsm.models import OUTPUT_NAMES


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return e3dpsm.create_model("tiny", height=64, width=96, train_window_ms=25.0).eval()


def _frame(model, batch: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    cfg = model.config
    return (torch.rand(batch, cfg.in_channels, cfg.height, cfg.width, generator=g) < 0.1).float()


def test_the_step_graph_is_model_step_in_the_specs_order(model) -> None:
    graph = StepGraph(model)
    names = [s.name for s in model.state_spec()]
    assert graph.state_names == names and graph.model is model
    state = model.init_state(2)
    with torch.no_grad():
        state = model.step(_frame(model, 2, 1), state, torch.tensor([20.0, 30.0]))[1]  # not the initial one
        lnes, window = _frame(model, 2, 2), torch.tensor([25.0, 50.0])
        got = graph(lnes, window, *(state[n] for n in names))
        outputs, new_state = model.step(lnes, state, window)
    assert len(got) == len(OUTPUT_NAMES) + len(names)
    for value, expected in zip(got, [*(outputs[k] for k in OUTPUT_NAMES), *(new_state[n] for n in names)]):
        torch.testing.assert_close(value, expected, rtol=0, atol=0)


def test_the_example_inputs_are_an_empty_frame_the_training_window_and_the_initial_states(model) -> None:
    lnes, window, *states = StepGraph(model).example_inputs(3)
    assert lnes.shape == (3, 2, 64, 96) and not lnes.any() and lnes.dtype == torch.float32
    torch.testing.assert_close(window, torch.full((3,), 25.0))
    initial = model.init_state(3)
    assert len(states) == len(initial)
    for value, name in zip(states, [s.name for s in model.state_spec()]):
        torch.testing.assert_close(value, initial[name], rtol=0, atol=0)
    assert StepGraph(model).example_inputs()[0].shape[0] == 1


def test_the_torch_stepper_is_model_step_in_numpy_without_gradients() -> None:
    torch.manual_seed(1)
    model = e3dpsm.create_model("tiny", height=64, width=96).train()
    stepper = TorchStepper(model)
    assert not model.training  # eval: BatchNorm's running statistics, no dropout
    state = stepper.init_state(2)
    expected_state = model.init_state(2)
    assert set(state) == set(expected_state) and all(isinstance(v, np.ndarray) for v in state.values())
    for name, value in expected_state.items():
        np.testing.assert_array_equal(state[name], value.numpy())
    assert stepper.init_state()[next(iter(state))].shape[0] == 1
    lnes = _frame(model, 2, 3).numpy()
    outputs, new_state = stepper.step(lnes, state, 33.0)
    with torch.no_grad():
        ref_out, ref_state = model.step(torch.from_numpy(lnes), {k: torch.from_numpy(v) for k, v in state.items()},
                                        torch.tensor([33.0]))
    assert set(outputs) == set(ref_out) and all(isinstance(v, np.ndarray) for v in outputs.values())
    for name in ref_out:
        np.testing.assert_array_equal(outputs[name], ref_out[name].numpy())
    for name in ref_state:
        np.testing.assert_array_equal(new_state[name], ref_state[name].numpy())
    other, _ = stepper.step(lnes, state, 20.0)  # the window is the one given
    assert not np.array_equal(other["pose"], outputs["pose"])


@pytest.fixture(scope="module")
def conv_relu(tmp_path_factory):
    weights = onnx.numpy_helper.from_array(np.random.default_rng(0).normal(size=(4, 2, 3, 3)).astype(np.float32), "w")
    graph = helper.make_graph(
        [helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]), helper.make_node("Relu", ["c"], ["y"])], "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2, 8, 8])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 8, 8])], [weights])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    path = tmp_path_factory.mktemp("ort") / "step.onnx"
    onnx.save(model, path)
    return path


@pytest.mark.parametrize("level, ops", [
    ("basic", [("", "Conv"), ("", "Relu")]),  # constant folding and the like only
    ("extended", [("com.microsoft", "FusedConv")]),  # the provider's fusions
    ("all", None),  # and NCHWc layouts: the provider's own domain
])
def test_each_level_writes_the_rewrites_it_stands_for(conv_relu, tmp_path, level, ops) -> None:
    import onnxruntime as ort

    target = tmp_path / "opt" / "step_ort.onnx"
    record = write_ort_optimized(conv_relu, target, level)
    written = onnx.load(str(target))
    got = [(n.domain, n.op_type) for n in written.graph.node]
    if ops is None:
        assert got and all(domain == "com.microsoft.nchwc" for domain, _ in got)
    else:
        assert got == ops
    assert record == {"path": "step_ort.onnx", "level": level, "onnxruntime": ort.__version__,
                      "provider": "CPUExecutionProvider", "bytes": target.stat().st_size,
                      "seconds": record["seconds"],
                      "note": "specific to this ONNX Runtime version and execution provider; load it with graph "
                              "optimisations disabled; the portable graph is the reference"}
    assert 0 < record["seconds"] == round(record["seconds"], 3)
    assert [p.name for p in target.parent.iterdir()] == ["step_ort.onnx"]
    x = np.random.default_rng(1).normal(size=(1, 2, 8, 8)).astype(np.float32)
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    same = [ort.InferenceSession(str(p), options if p == target else None, providers=["CPUExecutionProvider"])
            .run(None, {"x": x})[0] for p in (conv_relu, target)]
    np.testing.assert_allclose(same[1], same[0], rtol=1e-5, atol=1e-5)


def test_the_copy_is_written_through_a_hidden_onnx_temporary_and_timed(conv_relu, tmp_path, monkeypatch) -> None:
    import e3dpsm.utils.io as io

    temporaries = record_temporaries(monkeypatch, io)
    record = write_ort_optimized(conv_relu, tmp_path / "step_ort.onnx")
    assert len(temporaries) == 1 and temporaries[0].startswith(".step_ort.onnx.") and temporaries[0].endswith(".onnx")
    assert 0 < record["seconds"] < 60


def test_an_unknown_level_is_refused_and_nothing_written(conv_relu, tmp_path) -> None:
    assert ORT_LEVELS == ("basic", "extended", "all")
    with pytest.raises(ConfigError) as error:
        write_ort_optimized(conv_relu, tmp_path / "x.onnx", "max")
    assert str(error.value) == "unknown ONNX Runtime optimisation level 'max'; choose from ('basic', 'extended', 'all')"
    assert list(tmp_path.iterdir()) == []
    assert write_ort_optimized(conv_relu, tmp_path / "d.onnx")["level"] == "extended"  # the default
