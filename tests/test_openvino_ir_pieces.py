"""The ONNX -> OpenVINO IR converter (export/openvino_ir.py) on the numpy-sized toy step graph
(tests/_toy_step_graph.py): what each refusal says, a batch fixed with and without the states,
the conversion record, the precision read from the graph's metadata, the rt_info sections, and
fp32 weights left fp32. The stateful IR's steps are in test_openvino_stateful_pieces.py."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest

pytest.importorskip("openvino", reason="openvino (pip extra openvino) is not installed")

from _toy_step_graph import INIT, STATE, toy_lnes, toy_numpy_step, toy_step_graph  # noqa: E402
from e3dpsm.errors import ConfigError, DataError, InputError  # noqa: E402
from e3dpsm.export import openvino_ir  # noqa: E402
from e3dpsm.export.openvino_ir import (ConversionInfo, convert_step_graph, fix_batch, make_stateful,  # noqa: E402
                                       read_step_graph, save_ir)
from e3dpsm.graph_metadata import GraphMetadata, MetadataError  # noqa: E402
from e3dpsm.state import StateSpec, state_input_name, state_output_name  # noqa: E402


@pytest.fixture(scope="module")
def toy_onnx(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("toy") / "toy.onnx"
    onnx.save(toy_step_graph(), path)
    return path


def _shapes(model) -> dict[str, str]:
    return {p.get_any_name(): str(p.get_partial_shape()) for p in model.inputs}


def test_a_file_that_is_not_an_onnx_step_graph_is_one_line(toy_onnx, tmp_path) -> None:
    with pytest.raises(DataError) as error:
        read_step_graph(tmp_path / "missing.onnx")
    assert str(error.value) == f"model {tmp_path / 'missing.onnx'} does not exist"
    xml = tmp_path / "step.xml"
    xml.write_text("<net/>")
    with pytest.raises(InputError) as error:
        read_step_graph(xml)
    assert str(error.value) == f"{xml} is not an ONNX step graph (.onnx), as written by e3dpsm export / quantize"
    bare = toy_step_graph()
    del bare.metadata_props[:]
    onnx.save(bare, tmp_path / "bare.onnx")
    with pytest.raises(MetadataError):
        read_step_graph(tmp_path / "bare.onnx")
    model, meta, props = read_step_graph(toy_onnx)
    assert [s.name for s in meta.states] == [STATE] and props == {p.key: p.value for p in onnx.load(toy_onnx).metadata_props}


def test_a_batch_is_fixed_on_the_frame_and_window_and_on_the_states_when_asked(toy_onnx) -> None:
    s_in = state_input_name(STATE)
    model, meta, _ = read_step_graph(toy_onnx)
    assert _shapes(model) == {"lnes": "[?,2,2,3]", "window_ms": "[?]", s_in: "[?,3]"}
    fix_batch(model, meta, 4, states=False)
    assert _shapes(model) == {"lnes": "[4,2,2,3]", "window_ms": "[4]", s_in: "[?,3]"}
    model, meta, _ = read_step_graph(toy_onnx)
    fix_batch(model, meta, 3)
    assert _shapes(model) == {"lnes": "[3,2,2,3]", "window_ms": "[3]", s_in: "[3,3]"}
    other = GraphMetadata(states=(StateSpec("ghost", (3,)), StateSpec("absent", (1,))), inputs=meta.inputs,
                          outputs=meta.outputs, config=meta.config, joints=meta.joints)
    with pytest.raises(InputError) as error:
        fix_batch(model, other, 1)
    assert str(error.value) == "the graph lacks the inputs ['absent_in', 'ghost_in'] its metadata names"


@pytest.mark.parametrize("state, message", [
    (StateSpec("ghost", (3,)), "state 'ghost': the graph has no tensor 'ghost_in'"),
    (StateSpec(STATE, (3,), dtype="float16"), f"state '{STATE}' has dtype float16; only float32 states are supported"),
])
def test_states_the_graph_cannot_carry_are_refused_before_any_change(toy_onnx, state, message) -> None:
    model, meta, _ = read_step_graph(toy_onnx)
    fix_batch(model, meta, 1, states=False)
    bad = GraphMetadata(states=(state,), inputs=meta.inputs, outputs=meta.outputs, config=meta.config, joints=meta.joints)
    before = sorted(p.get_any_name() for p in model.inputs)
    with pytest.raises(InputError) as error:
        make_stateful(model, bad, 1)
    assert str(error.value) == message and sorted(p.get_any_name() for p in model.inputs) == before


def test_a_stateful_model_starts_from_the_metadatas_initial_state(toy_onnx) -> None:
    import openvino as ov

    model, meta, _ = read_step_graph(toy_onnx)
    fix_batch(model, meta, 1, states=False)
    assert make_stateful(model, meta, 1) == [STATE]
    assert sorted(p.get_any_name() for p in model.inputs) == ["lnes", "window_ms"]
    assert state_output_name(STATE) not in {p.get_any_name() for p in model.outputs}
    assert [v.get_info().variable_id for v in model.get_variables()] == [STATE]
    request = ov.Core().compile_model(model, "CPU").create_infer_request()
    lnes = toy_lnes(1, seed=3)
    out = request.infer({"lnes": lnes, "window_ms": np.float32([20.0])})
    expected = toy_numpy_step(lnes, np.asarray([INIT]), [20.0])
    np.testing.assert_allclose(out["pose"], 2 * expected, rtol=1e-5)


@pytest.mark.parametrize("quantization, precision", [
    (None, "fp32"), ({"mode": "int8"}, "int8"), ({"precision": "fp16"}, "fp16"),
    ({"mode": "int8-weights", "precision": "fp16"}, "int8-weights"), ({"mode": None, "precision": "int8"}, "int8"),
])
def test_the_precision_is_the_graphs_quantisation_mode(quantization, precision) -> None:
    meta = GraphMetadata(states=(), inputs={}, outputs=[], config={}, joints=[], quantization=quantization)
    assert openvino_ir._precision(meta) == precision


@pytest.mark.parametrize("options, message", [
    ({"stateful": False, "batch": 0}, "batch must be >= 1, got 0"),
    ({"stateful": True, "batch": 2}, "--stateful supports batch 1 (one stream per infer request), got 2; open one "
                                     "request per stream"),
])
def test_a_batch_the_conversion_cannot_make_is_refused(toy_onnx, options, message) -> None:
    with pytest.raises(ConfigError) as error:
        convert_step_graph(toy_onnx, **options)
    assert str(error.value) == message


@pytest.mark.parametrize("stateful, batch, expected_batch, inputs", [
    (False, None, None, ["lnes", "window_ms", state_input_name(STATE)]),
    (False, 2, 2, ["lnes", "window_ms", state_input_name(STATE)]),
    (True, None, 1, ["lnes", "window_ms"]),
])
def test_the_conversion_record_says_what_was_done(toy_onnx, stateful, batch, expected_batch, inputs) -> None:
    model, info = convert_step_graph(toy_onnx, stateful=stateful, batch=batch)
    assert info == ConversionInfo(source="toy.onnx", stateful=stateful, batch=expected_batch, precision="fp32",
                                  inputs=inputs, outputs=info.outputs, variables=[STATE] if stateful else [])
    assert "pose" in info.outputs and (state_output_name(STATE) in info.outputs) is not stateful
    for key, value in info.to_dict().items():
        assert json.loads(model.get_rt_info(["e3dpsm_openvino", key]).astype(str)) == value
    props = {p.key: p.value for p in onnx.load(toy_onnx).metadata_props}
    for key, value in props.items():
        assert model.get_rt_info(["e3dpsm", key]).astype(str) == value
    assert model.get_rt_info(["runtime_options", "DYNAMIC_QUANTIZATION_GROUP_SIZE"]).astype(str) == "0"
    if batch:
        assert _shapes(model)["lnes"] == f"[{batch},2,2,3]"
        assert _shapes(model)[state_input_name(STATE)] == f"[{batch},3]"  # explicit states fixed too
    if stateful:  # the variables' nodes are named by their state, as an IR reader sees them
        names = {op.get_friendly_name() for op in model.get_ops()}
        assert {f"{STATE}/init", f"{STATE}/read", f"{STATE}/assign"} <= names


def test_one_is_a_batch_and_the_record_lists_default_empty() -> None:
    assert ConversionInfo("g.onnx", False, None, "fp32").to_dict() == {
        "source": "g.onnx", "stateful": False, "batch": None, "precision": "fp32", "inputs": [], "outputs": [],
        "variables": []}


def test_a_batch_of_one_is_accepted_without_states(toy_onnx) -> None:
    model, info = convert_step_graph(toy_onnx, stateful=False, batch=1)
    assert info.batch == 1 and _shapes(model)["lnes"] == "[1,2,2,3]"


def test_the_ir_keeps_fp32_weights_fp32(tmp_path) -> None:
    import openvino as ov
    import openvino.opset13 as ops

    weights = np.linspace(-1, 1, 12, dtype=np.float32).reshape(3, 4) / 3  # not exact in fp16
    x = ops.parameter([1, 3], ov.Type.f32, name="x")
    model = ov.Model([ops.matmul(x, ops.constant(weights), False, False)], [x], "m")
    xml, weights_file = save_ir(model, tmp_path / "m.xml")
    assert (xml, weights_file) == (tmp_path / "m.xml", tmp_path / "m.bin") and weights_file.is_file()
    read = ov.Core().read_model(str(xml))
    constants = [op for op in read.get_ops() if op.get_type_name() == "Constant"]
    assert [c.get_element_type() for c in constants] == [ov.Type.f32]
    np.testing.assert_array_equal(constants[0].get_data(), weights)
