"""The OpenVINO step session (runtime/openvino_session.py) on a toy ONNX graph written with
onnx.helper: the numbers it steps against numpy, the outputs copied out of the request, a port
with several names, the compile options it sets, the heavy layers it counts, and each refusal
whole. The exported tiny runs on OpenVINO in test_openvino_executed.py and elsewhere; the
DeformConv rule against an explicit loop in test_deform_conv_export.py."""
from __future__ import annotations

import sys
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("openvino", reason="openvino (pip extra openvino) is not installed")

import onnx  # noqa: E402
from onnx import TensorProto, helper  # noqa: E402

from _golden_fakes import FRAME, STATE, STATE_SHAPE  # noqa: E402
from e3dpsm.errors import ConfigError, DataError  # noqa: E402
from e3dpsm.graph_metadata import GraphMetadata  # noqa: E402
from e3dpsm.runtime import openvino_session  # noqa: E402
from e3dpsm.runtime.openvino_session import (OpenVINOStepSession, compile_config, count_heavy_layers,  # noqa: E402
                                             executed_layers, read_openvino_model)
from e3dpsm.state import StateSpec, state_input_name, state_output_name  # noqa: E402

S_IN, S_OUT = state_input_name(STATE), state_output_name(STATE)
MIX = np.arange(36, dtype=np.float32).reshape(6, 6) / 36  # the toy's state transition (a MatMul)


def toy_step(lnes, window, state):
    window = np.asarray(window, np.float32).reshape(-1)
    return ((2 * lnes + window[:, None, None, None]).astype(np.float32),
            (state @ MIX + window[:, None]).astype(np.float32))


def toy_graph() -> onnx.ModelProto:
    """pose = 2 * lnes + window_ms; state_out = state_in @ MIX + window_ms; `pose_again`, an
    Identity of pose, is a second name of the same output port once OpenVINO fuses it."""
    frame = ["batch", *FRAME]
    nodes = [
        helper.make_node("Reshape", ["window_ms", "to_4d"], ["window_4d"]),
        helper.make_node("Mul", ["lnes", "two"], ["doubled"]),
        helper.make_node("Add", ["doubled", "window_4d"], ["pose"]),
        helper.make_node("Identity", ["pose"], ["pose_again"]),
        helper.make_node("MatMul", [S_IN, "mix"], ["mixed"]),
        helper.make_node("Unsqueeze", ["window_ms", "axis1"], ["window_2d"]),
        helper.make_node("Add", ["mixed", "window_2d"], [S_OUT]),
    ]
    initializers = [helper.make_tensor("two", TensorProto.FLOAT, [], [2.0]),
                    helper.make_tensor("to_4d", TensorProto.INT64, [4], [-1, 1, 1, 1]),
                    helper.make_tensor("axis1", TensorProto.INT64, [1], [1]),
                    onnx.numpy_helper.from_array(MIX, "mix")]
    graph = helper.make_graph(
        nodes, "toy",
        [helper.make_tensor_value_info("lnes", TensorProto.FLOAT, frame),
         helper.make_tensor_value_info("window_ms", TensorProto.FLOAT, ["batch"]),
         helper.make_tensor_value_info(S_IN, TensorProto.FLOAT, ["batch", *STATE_SHAPE])],
        [helper.make_tensor_value_info("pose", TensorProto.FLOAT, frame),
         helper.make_tensor_value_info("pose_again", TensorProto.FLOAT, frame),
         helper.make_tensor_value_info(S_OUT, TensorProto.FLOAT, ["batch", *STATE_SHAPE])],
        initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    meta = GraphMetadata(states=(StateSpec(STATE, STATE_SHAPE),),
                         inputs={"frame": {"name": "lnes", "shape": frame}, "window": {"name": "window_ms"}},
                         outputs=[{"name": "pose"}, {"name": "pose_again"}], config={"variant": "toy"},
                         joints=[f"j{i}" for i in range(16)])
    helper.set_model_props(model, meta.to_props())
    onnx.checker.check_model(model)
    return model


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    path = tmp_path_factory.mktemp("toy") / "step.onnx"
    onnx.save(toy_graph(), path)
    return path


def test_a_step_gives_the_toys_outputs_and_carries_its_state(toy) -> None:
    session = OpenVINOStepSession(toy, threads=1)
    assert session.path == toy and session.meta.output_names == ["pose", "pose_again"]
    rng = np.random.default_rng(0)
    state = session.init_state(1)
    for window in (20.0, 33.0):
        lnes = rng.uniform(0, 1, (1, *FRAME)).astype(np.float32)
        outputs, new_state = session.step(lnes, state, window)
        pose, expected_state = toy_step(lnes, [window], state[STATE])
        assert list(outputs) == ["pose", "pose_again"]
        np.testing.assert_allclose(outputs["pose"], pose, rtol=0, atol=1e-5)
        np.testing.assert_array_equal(outputs["pose_again"], outputs["pose"])
        np.testing.assert_allclose(new_state[STATE], expected_state, rtol=1e-6, atol=1e-5)
        state = new_state


def test_outputs_are_copies_the_next_inference_does_not_overwrite(toy) -> None:
    session = OpenVINOStepSession(toy, threads=1)
    lnes = np.ones((2, *FRAME), np.float32)
    first, first_state = session.run_feeds(session.feeds(lnes, session.init_state(2), np.float32([1.0, 2.0])))
    kept = {k: v.copy() for k, v in first.items()}, first_state[STATE].copy()
    session.run_feeds(session.feeds(3 * lnes, first_state, np.float32([5.0, 6.0])))
    for name in first:
        np.testing.assert_array_equal(first[name], kept[0][name])
    np.testing.assert_array_equal(first_state[STATE], kept[1])
    np.testing.assert_allclose(first["pose"][:, 0, 0, 0], [3.0, 4.0], rtol=0, atol=1e-6)


def test_a_non_contiguous_input_is_bound_as_its_values(toy) -> None:
    session = OpenVINOStepSession(toy, threads=1)
    wide = np.random.default_rng(2).uniform(0, 1, (1, FRAME[0], FRAME[1], 2 * FRAME[2])).astype(np.float32)
    lnes = wide[..., ::2]  # a strided view
    feeds = session.feeds(np.ascontiguousarray(lnes), session.init_state(1), np.float32([20.0]))
    feeds["lnes"] = lnes
    outputs, _ = session.run_feeds(feeds)
    np.testing.assert_allclose(outputs["pose"], toy_step(lnes, [20.0], np.zeros((1, 6), np.float32))[0],
                               rtol=0, atol=1e-5)


def test_the_compile_options_are_the_graphs_own_arithmetic(toy, monkeypatch) -> None:
    assert compile_config(None) == {"INFERENCE_PRECISION_HINT": "f32", "DYNAMIC_QUANTIZATION_GROUP_SIZE": 0}
    assert compile_config(0) == compile_config(None)
    assert compile_config(3.0)["INFERENCE_NUM_THREADS"] == 3 and type(compile_config(3.0)["INFERENCE_NUM_THREADS"]) is int
    assert compile_config(2, {"DYNAMIC_QUANTIZATION_GROUP_SIZE": 32, "X": 1}) == {
        "INFERENCE_PRECISION_HINT": "f32", "DYNAMIC_QUANTIZATION_GROUP_SIZE": 32, "X": 1, "INFERENCE_NUM_THREADS": 2}
    with pytest.raises(ConfigError) as error:
        compile_config(1, precision="f16")
    assert str(error.value) == "unknown OpenVINO precision 'f16'; choose one of f32, bf16"
    import e3dpsm.utils.isa as isa

    monkeypatch.setattr(isa, "bf16_unavailable_reason", lambda: None)
    assert compile_config(1, precision="bf16")["INFERENCE_PRECISION_HINT"] == "bf16"
    monkeypatch.setattr(isa, "bf16_unavailable_reason", lambda: "no avx512_bf16")
    with pytest.raises(ConfigError) as error:
        compile_config(1, precision="bf16")
    assert str(error.value) == "bf16 needs a CPU with bf16 units: no avx512_bf16; run f32 (or int8) here"
    session = OpenVINOStepSession(toy, threads=1, config={"PERFORMANCE_HINT": "LATENCY"})
    compiled = session.compiled
    assert compiled.get_property("INFERENCE_NUM_THREADS") == 1
    assert "float32" in str(compiled.get_property("INFERENCE_PRECISION_HINT"))
    assert str(compiled.get_property("PERFORMANCE_HINT")).endswith("LATENCY")


def test_the_heavy_layers_are_counted_by_their_run_time_precision(toy) -> None:
    layers = [("Convolution", "U8"), ("Convolution", "U8"), ("MatMul", "FP32"), ("Eltwise", "FP32"), (None, "FP32"),
              ("FullyConnected", "BF16"), ("Deconvolution", "FP32")]
    assert count_heavy_layers(layers) == {"Convolution U8": 2, "Deconvolution FP32": 1, "FullyConnected BF16": 1,
                                          "MatMul FP32": 1}
    assert list(count_heavy_layers(reversed(layers))) == sorted(count_heavy_layers(layers))
    executed = executed_layers(OpenVINOStepSession(toy, threads=1).compiled)
    assert sum(executed.values()) == 1 and next(iter(executed)).split()[0] in ("FullyConnected", "MatMul")
    assert next(iter(executed)).split()[1] == "f32"


def test_a_port_is_named_by_the_contract_first() -> None:
    port = SimpleNamespace(get_names=lambda: {"z_cast", "pose", "a_first"}, get_any_name=lambda: "z_cast")
    assert openvino_session._contract_name(port, {"pose", "other"}) == "pose"
    assert openvino_session._contract_name(port, {"a_first", "pose"}) == "a_first"  # sorted: one answer always
    assert openvino_session._contract_name(port, {"else"}) == "z_cast"


def test_onnx_graphs_are_protected_and_ir_files_read_as_written(toy, tmp_path, monkeypatch) -> None:
    import openvino as ov

    protected = []
    monkeypatch.setattr(openvino_session, "protect_dequantization", protected.append)
    core, model = read_openvino_model(toy)
    assert protected == [model]
    ov.save_model(model, tmp_path / "step.xml")
    read_openvino_model(tmp_path / "step.xml")
    assert len(protected) == 1


def test_refusals_are_one_line(tmp_path, monkeypatch) -> None:
    with pytest.raises(DataError) as error:
        read_openvino_model(tmp_path / "missing.onnx")
    assert str(error.value) == f"model {tmp_path / 'missing.onnx'} does not exist"
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"\x08\x07" + b"\xff" * 64)
    with pytest.raises(DataError) as error:
        read_openvino_model(garbage)
    message = str(error.value)
    assert message.startswith(f"OpenVINO cannot read {garbage}: ") and "\n" not in message
    assert len(message) <= len(f"OpenVINO cannot read {garbage}: ") + 300
    monkeypatch.setitem(sys.modules, "openvino", None)
    assert openvino_session.openvino_available() == (
        False, "openvino is not installed (pip install 'e3dpsm[openvino]')")
    with pytest.raises(ConfigError) as error:
        read_openvino_model(garbage)
    assert str(error.value) == "openvino is not installed (pip install 'e3dpsm[openvino]')"


def test_available_says_nothing_when_openvino_is_there() -> None:
    assert openvino_session.openvino_available() == (True, "")


def test_the_inputs_are_bound_without_a_copy_and_every_output_is_named(toy) -> None:
    session = OpenVINOStepSession(toy, threads=1)
    assert session.output_names_all() == ["pose", "pose_again", "s_out"]
    assert session.input_names() == ["lnes", "window_ms", "s_in"]
    feeds = session.feeds(np.ones((1, *FRAME), np.float32), session.init_state(1), np.float32([20.0]))
    session.run_raw(feeds)
    bound = session._request.get_tensor(session._input_ports["lnes"]).data
    assert np.shares_memory(bound, feeds["lnes"])  # shared memory: the step copies nothing in


def test_an_unreadable_models_error_is_its_first_line_capped(tmp_path, monkeypatch) -> None:
    class Refusing:
        def read_model(self, path):
            raise RuntimeError("x" * 299 + "yz" + "\nsecond line")

    path = tmp_path / "step.onnx"
    path.write_bytes(b"anything")
    monkeypatch.setattr(openvino_session, "openvino_core", Refusing)
    with pytest.raises(DataError) as error:
        read_openvino_model(path)
    assert str(error.value) == f"OpenVINO cannot read {path}: " + "x" * 299 + "y"
