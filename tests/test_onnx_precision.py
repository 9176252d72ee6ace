"""The compute-node census (quantize/census.py) against hand-made QDQ graphs whose answer is
known by construction, and the private copies of the states quantised nodes read."""
from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.onnx_precision import compute_precisions, out_of_8_bits, precision_counts


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
