"""The compute-node census (quantize/census.py) against hand-made QDQ graphs whose answer is
known by construction, and the recurrent projections' precision stage on injected errors."""
from __future__ import annotations

import numpy as np
import onnx
import pytest
from _precision_helpers import recurrent_evaluator, recurrent_plan
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.quantize.census import compute_precisions, out_of_8_bits, precision_counts
from e3dpsm.quantize.precision import quantise_recurrent_compute


def _qdq_graph() -> onnx.ModelProto:
    """x -> [a8w8 MatMul] -> [a16w8 MatMul] -> [a16w16 MatMul] -> [float MatMul] -> [a8 x a8 MatMul]
    -> [a16 activation, float weight MatMul] -> y. Each weight is 4 x 4."""
    inits: list[onnx.TensorProto] = []
    nodes: list[onnx.NodeProto] = []

    def const(name: str, value: np.ndarray) -> str:
        inits.append(numpy_helper.from_array(value, name))
        return name

    def activation(x: str, zero_dtype: np.dtype | None, tag: str, output_dtype: int | None = None) -> str:
        inputs = [x, const(f"{tag}.s", np.float32(0.1))]
        if zero_dtype is not None:
            inputs.append(const(f"{tag}.z", np.zeros((), zero_dtype)))
        attrs = {"output_dtype": output_dtype} if output_dtype else {}
        nodes.append(helper.make_node("QuantizeLinear", inputs, [f"{tag}.q"], name=f"{tag}_q", **attrs))
        nodes.append(helper.make_node("DequantizeLinear", [f"{tag}.q", *inputs[1:]], [f"{tag}.dq"], name=f"{tag}_dq"))
        return f"{tag}.dq"

    def weight(dtype: np.dtype, tag: str) -> str:
        w = const(f"{tag}.w", np.ones((4, 4), dtype))
        nodes.append(helper.make_node("DequantizeLinear", [w, const(f"{tag}.ws", np.float32(0.01))], [f"{tag}.wdq"],
                                      name=f"{tag}_wdq"))
        return f"{tag}.wdq"

    x = "x"
    plan = [("a8w8", np.uint8, np.int8), ("a16w8", np.uint16, np.int8), ("a16w16", np.uint16, np.int16),
            ("half_float", np.uint8, None)]
    for tag, act, wt in plan:
        a = activation(x, act, tag)
        w = weight(wt, tag) if wt is not None else const(f"{tag}.fw", np.ones((4, 4), np.float32))
        nodes.append(helper.make_node("MatMul", [a, w], [f"{tag}.y"], name=tag))
        x = f"{tag}.y"
    # Two activations, 8-bit each (attention's Q x K^T); a Q without zero point writes uint8.
    left = activation(x, None, "left")
    right = activation(x, None, "right")
    nodes.append(helper.make_node("MatMul", [left, right], ["aa.y"], name="act_by_act"))
    # The same at 16 bits: no weights, so int16 (not int16w16).
    wide = [activation(x, np.uint16, f"wide{i}") for i in range(2)]
    nodes.append(helper.make_node("MatMul", wide, ["wide.y"], name="act_by_act16"))
    nodes.append(helper.make_node("Add", ["aa.y", "wide.y"], ["aa.sum"], name="join"))
    # opset 21's output_dtype instead of a zero point: 16 bits.
    a16 = activation("aa.sum", None, "od", output_dtype=TensorProto.UINT16)
    nodes.append(helper.make_node("MatMul", [a16, weight(np.int8, "od")], ["y"], name="output_dtype16"))
    graph = helper.make_graph(nodes, "census", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [4, 4])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [4, 4])], inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 21)])


def test_census_reads_each_compute_node_precision_off_the_graph() -> None:
    model = _qdq_graph()
    onnx.checker.check_model(model)
    labels = compute_precisions(model)
    assert labels == {"a8w8": "int8", "a16w8": "int16", "a16w16": "int16w16", "half_float": "float",
                      "act_by_act": "int8", "act_by_act16": "int16", "output_dtype16": "int16"}
    assert precision_counts(labels) == {"int8": 2, "int16": 3, "int16w16": 1, "float": 1}
    assert out_of_8_bits(labels) == 5


def test_census_names_other_mixes() -> None:
    model = _qdq_graph()
    for init in model.graph.initializer:  # 8-bit activations with 16-bit weights: no label of its own
        if init.name == "a8w8.w":
            init.CopyFrom(numpy_helper.from_array(np.ones((4, 4), np.int16), init.name))
    labels = compute_precisions(model)
    assert labels["a8w8"] == "a8w16" and precision_counts(labels)["a8w16"] == 1


# -- the recurrent projections' stage, on injected errors -------------------------------------

def test_recurrent_projections_all_at_int8_when_they_fit() -> None:
    cost8 = {"drive": 0.05, "read": 0.1}
    plan = quantise_recurrent_compute(recurrent_plan(), [["drive"], ["read"]], recurrent_evaluator(cost8, cost8, cost8=cost8))
    assert plan.int8 == ["drive", "read"] and plan.int16 == ["x"] and plan.float_nodes == ["f"]
    assert plan.error_pct == pytest.approx(0.65) and [t["label"] for t in plan.trials][1:] == ["recurrent_int8_all"]
    assert {c.node: c.precision for c in plan.choices} == {"x": "int16", "drive": "int8", "read": "int8"}
    assert plan.to_dict()["int8_recurrent_nodes"] == ["drive", "read"]


def test_recurrent_projections_all_at_int16_then_each_back_at_int8_where_it_fits() -> None:
    # All at int8: 0.5 + 0.25 + 0.1 = 0.85 > 0.7; all at int16: 0.5 + 0.05 + 0.1 = 0.65. Then
    # each back at 8 bits: drive 0.65 - 0.05 + 0.25 = 0.85 (stays int16); read 0.65 - 0.1 +
    # 0.1 = 0.65 (int8, costs nothing more).
    cost16, cost8 = {"drive": 0.05, "read": 0.1}, {"drive": 0.25, "read": 0.1}
    plan = quantise_recurrent_compute(recurrent_plan(), [["drive"], ["read"]], recurrent_evaluator(cost16, cost16, cost8=cost8))
    assert plan.int8 == ["read"] and plan.int16 == ["x", "drive"] and plan.int16w16 == ["w"]
    assert plan.float_nodes == ["f"] and plan.error_pct == pytest.approx(0.65)
    assert [t["label"] for t in plan.trials][1:] == [
        "recurrent_int8_all", "recurrent_int16_all", "recurrent_int8_drive", "recurrent_int8_read"]
    by_node = {c.node: c for c in plan.choices}
    assert by_node["read"].precision == "int8" and by_node["read"].reason.startswith("recurrent group: int8 meets")
    # drive's int8 figure is the trial that decided it, alone at 8 bits
    assert by_node["drive"].precision == "int16" and by_node["drive"].errors["int8"] == pytest.approx(0.85)
    assert plan.trials[-1]["int8_recurrent_nodes"] == 1 and plan.trials[-1]["int16_nodes"] == 2


def test_recurrent_projections_all_at_int16_when_they_fit() -> None:
    cost16 = {"drive": 0.05, "read": 0.1}
    plan = quantise_recurrent_compute(recurrent_plan(), [["drive"], ["read"]], recurrent_evaluator(cost16, {"drive": 0.0, "read": 0.0}))
    assert plan.int16 == ["x", "drive", "read"] and plan.int16w16 == ["w"] and plan.float_nodes == ["f"]
    assert plan.int8 == [] and plan.error_pct == pytest.approx(0.65)
    assert [t["label"] for t in plan.trials][1:] == [
        "recurrent_int8_all", "recurrent_int16_all", "recurrent_int8_drive", "recurrent_int8_read"]
    choice = {c.node: c for c in plan.choices}["read"]
    assert choice.precision == "int16" and choice.reason.startswith("recurrent group: int16 meets")
    assert "int8 1.550% over" in choice.reason  # alone at 8 bits, drive at int16: 0.5 + 0.05 + 1.0


def test_recurrent_projections_one_at_a_time_int8_then_int16_then_int16w16_then_float() -> None:
    # All at int8: 0.5 + 0.3 + 0.3 + 0.04 > 0.7; all at int16: 0.5 + 0.65 > 0.7; all at
    # int16w16: 0.5 + 0.35 > 0.7. Then in order: drive int8 0.8, int16 0.55 (kept); gain int8
    # 0.85, int16 0.85, int16w16 0.6 (kept); read int8 0.64 (kept: the cheapest that fits).
    cost8 = {"drive": 0.3, "gain": 0.3, "read": 0.04}
    cost16 = {"drive": 0.05, "gain": 0.3, "read": 0.3}
    cost_w16 = {"drive": 0.01, "gain": 0.05, "read": 0.29}
    plan = quantise_recurrent_compute(recurrent_plan(), [["drive"], ["gain"], ["read"]], recurrent_evaluator(cost16, cost_w16, cost8=cost8))
    assert plan.int16 == ["x", "drive"] and plan.int16w16 == ["w", "gain"] and plan.int8 == ["read"]
    assert plan.float_nodes == ["f"] and plan.error_pct == pytest.approx(0.64)
    by_node = {c.node: c for c in plan.choices}
    assert by_node["gain"].precision == "int16w16" and by_node["gain"].errors["int16"] == pytest.approx(0.85)
    assert by_node["read"].precision == "int8"
    assert [t["label"] for t in plan.trials][1:] == [
        "recurrent_int8_all", "recurrent_int16_all", "recurrent_int16w16_all", "recurrent_int8_drive",
        "recurrent_int16_drive", "recurrent_int8_gain", "recurrent_int16_gain", "recurrent_int16w16_gain",
        "recurrent_int8_read"]


def test_a_recurrent_projection_that_fits_nowhere_stays_float() -> None:
    cost = {"read": 0.3}
    plan = quantise_recurrent_compute(recurrent_plan(), [["read"]], recurrent_evaluator(cost, {"read": 0.29}, cost8={"read": 0.4}))
    assert plan.float_nodes == ["f", "read"] and plan.int8 == [] and plan.int16 == ["x"]
    by_node = {c.node: c for c in plan.choices}
    # float: the graph with every recurrent projection in float, the plan this stage started from
    assert by_node["read"].precision == "float" and "int16w16 0.790% over" in by_node["read"].reason
    assert by_node["read"].errors == pytest.approx({"int8": 0.9, "int16": 0.8, "int16w16": 0.79, "float": 0.5})


def test_a_unit_that_shares_an_input_leaves_8_bits_together() -> None:
    # drive_re and drive_im read one tensor: tried back at int8 together (0.65 - 0.1 + 0.1 =
    # 0.65 fits); alone, drive_re would have fitted and drive_im not, which no graph can be.
    cost16, cost8 = {"drive_re": 0.05, "drive_im": 0.05, "read": 0.05}, {"drive_re": 0.0, "drive_im": 0.1, "read": 0.5}
    plan = quantise_recurrent_compute(recurrent_plan(), [["drive_re", "drive_im"], ["read"]],
                                      recurrent_evaluator(cost16, cost16, cost8=cost8))
    assert plan.int8 == ["drive_re", "drive_im"] and plan.int16 == ["x", "read"]
    assert [t["label"] for t in plan.trials][1:] == [
        "recurrent_int8_all", "recurrent_int16_all", "recurrent_int8_drive_re+drive_im", "recurrent_int8_read"]
    by_node = {c.node: c for c in plan.choices}
    assert by_node["drive_re"].errors == by_node["drive_im"].errors


def test_nodes_reading_a_widened_tensor_are_not_tried_at_int8() -> None:
    # read's input is 16-bit already (a ranked node at int16 reads it too): no int8 graph with
    # it is tried, not even all at once; drive still is.
    cost16, cost8 = {"drive": 0.05, "read": 0.05}, {"drive": 0.0, "read": 0.0}
    plan = quantise_recurrent_compute(recurrent_plan(), [["drive"], ["read"]], recurrent_evaluator(cost16, cost16, cost8=cost8),
                                      no_int8={"read"})
    assert plan.int8 == ["drive"] and plan.int16 == ["x", "read"]
    assert [t["label"] for t in plan.trials][1:] == ["recurrent_int16_all", "recurrent_int8_drive"]
    assert "int8" not in {c.node: c for c in plan.choices}["read"].errors


def test_units_must_be_sequences_of_names() -> None:
    with pytest.raises(TypeError, match="units are sequences of node names"):
        quantise_recurrent_compute(recurrent_plan(), ["drive", "read"], recurrent_evaluator({}, {}))


def test_shared_input_units_group_the_readers_of_one_activation() -> None:
    from e3dpsm.quantize.graph_groups import shared_input_units

    w = [numpy_helper.from_array(np.ones((2, 2), np.float32), f"w{i}") for i in range(4)]
    nodes = [helper.make_node("MatMul", ["a", "w0"], ["y0"], name="re"),
             helper.make_node("MatMul", ["b", "w0"], ["y1"], name="other"),  # shares only a weight
             helper.make_node("MatMul", ["a", "w1"], ["y2"], name="im"),
             helper.make_node("MatMul", ["y2", "w2"], ["y3"], name="chain"),
             helper.make_node("Gemm", ["b", "w3"], ["y4"], name="gemm")]
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info(t, TensorProto.FLOAT, [1, 2]) for t in "ab"],
                              [helper.make_tensor_value_info(f"y{i}", TensorProto.FLOAT, [1, 2]) for i in (0, 1, 3, 4)],
                              w)
    model = helper.make_model(graph)
    assert shared_input_units(model, ["re", "other", "im", "chain", "gemm"]) == [["re", "im"], ["other", "gemm"],
                                                                                 ["chain"]]
    assert shared_input_units(model, ["chain", "im"]) == [["chain"], ["im"]]


def test_recurrent_stage_spends_nothing_when_the_plan_is_over_its_target() -> None:
    over = recurrent_plan(error=0.8, target=0.7)
    assert quantise_recurrent_compute(over, [["drive"]], recurrent_evaluator({"drive": 0.0}, {"drive": 0.0})) is over
    fits = recurrent_plan()
    assert quantise_recurrent_compute(fits, [], recurrent_evaluator({}, {})) is fits


def test_a_state_read_gets_its_own_copy_and_the_function_is_unchanged() -> None:
    import onnxruntime as ort

    from e3dpsm.quantize.graph_groups import isolate_state_reads

    f32 = TensorProto.FLOAT
    graph = helper.make_graph(
        [helper.make_node("Mul", ["x", "decay"], ["state"], name="update"),
         helper.make_node("MatMul", ["state", "w"], ["y"], name="read"),
         helper.make_node("MatMul", ["x", "w"], ["z"], name="drive")],
        "step", [helper.make_tensor_value_info("x", f32, [2, 3])],
        [helper.make_tensor_value_info("y", f32, [2, 3]), helper.make_tensor_value_info("state", f32, [2, 3]),
         helper.make_tensor_value_info("z", f32, [2, 3])],
        [numpy_helper.from_array(np.full((2, 3), 0.9, np.float32), "decay"),
         numpy_helper.from_array(np.arange(9, dtype=np.float32).reshape(3, 3), "w")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    x = np.random.default_rng(0).normal(size=(2, 3)).astype(np.float32)
    before = ort.InferenceSession(model.SerializeToString()).run(None, {"x": x})
    assert isolate_state_reads(model, ["read", "drive", "update"]) == ["read"]  # only a node reading a graph output
    onnx.checker.check_model(model)
    producer = {o: n for n in model.graph.node for o in n.output}
    assert producer["state"].name == "update"  # the graph output is still the float update's
    read = next(n for n in model.graph.node if n.name == "read")
    assert producer[read.input[0]].op_type == "Identity" and producer[read.input[0]].input[0] == "state"
    after = ort.InferenceSession(model.SerializeToString()).run(None, {"x": x})
    for a, b in zip(before, after):
        np.testing.assert_array_equal(a, b)
