"""Compute outputs left in float where no quantised op reads them (quantize/outputs.py),
checked on a hand-built QDQ graph against numpy."""
from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.errors import ConfigError
from e3dpsm.quantize import QuantizeOptions
from e3dpsm.quantize.outputs import dequantised_outputs

RNG = np.random.default_rng(0)
W1 = RNG.integers(-127, 128, size=(4, 6)).astype(np.int8)
W2 = RNG.integers(-127, 128, size=(6, 3)).astype(np.int8)
BIAS = RNG.normal(size=6).astype(np.float32)
SX, SW, SY = 0.02, 0.01, 0.05  # the output step SY is coarse: its rounding is visible


def _qdq(name: str, tensor: str, scale: float) -> list[onnx.NodeProto]:
    return [helper.make_node("QuantizeLinear", [tensor, f"{name}.s", f"{name}.z"], [f"{name}.q"], name=f"q_{name}"),
            helper.make_node("DequantizeLinear", [f"{name}.q", f"{name}.s", f"{name}.z"], [f"{name}.dq"],
                             name=f"dq_{name}")]


def _graph() -> onnx.ModelProto:
    """x -> QDQ -> MatMul(W1) -> QDQ -> Add(bias) -> y (a float reader: the pair only rounds),
    and MatMul(W1) -> QDQ -> Reshape -> MatMul(W2) -> y2 from a second MatMul whose input pair
    sits before a Reshape (a quantised reader: the pair stays)."""
    nodes = [
        *_qdq("x", "x", SX),
        helper.make_node("DequantizeLinear", ["w1", "w.s"], ["w1.dq"], name="dq_w1"),
        helper.make_node("MatMul", ["x.dq", "w1.dq"], ["h"], name="first"),
        *_qdq("h", "h", SY),
        helper.make_node("Add", ["h.dq", "bias"], ["y"], name="add"),
        helper.make_node("MatMul", ["x.dq", "w1.dq"], ["g"], name="second"),
        *_qdq("g", "g", SY),
        helper.make_node("Reshape", ["g.dq", "shape"], ["g2"], name="reshape"),
        helper.make_node("DequantizeLinear", ["w2", "w.s"], ["w2.dq"], name="dq_w2"),
        helper.make_node("MatMul", ["g2", "w2.dq"], ["y2"], name="third"),
    ]
    inits = [numpy_helper.from_array(np.array(v, np.float32), n) for n, v in
             (("x.s", SX), ("h.s", SY), ("g.s", SY), ("w.s", SW))]
    inits += [numpy_helper.from_array(np.array(128, np.uint8), n) for n in ("x.z", "h.z", "g.z")]
    inits += [numpy_helper.from_array(W1, "w1"), numpy_helper.from_array(W2, "w2"),
              numpy_helper.from_array(BIAS, "bias"), numpy_helper.from_array(np.array([2, 6], np.int64), "shape")]
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 4])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2, 6]),
                               helper.make_tensor_value_info("y2", TensorProto.FLOAT, [2, 3])], inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def _run(model: onnx.ModelProto, x: np.ndarray) -> dict[str, np.ndarray]:
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    return dict(zip(["y", "y2"], session.run(["y", "y2"], {"x": x})))


def _round(v: np.ndarray, scale: float) -> np.ndarray:
    return (np.clip(np.round(v / scale) + 128, 0, 255) - 128) * scale


def test_a_pair_no_quantised_op_reads_is_removed_and_the_output_is_exact() -> None:
    x = RNG.normal(size=(2, 4)).astype(np.float32)
    xq = _round(x, SX)
    w1 = W1.astype(np.float64) * SW
    exact_y = xq @ w1 + BIAS  # numpy reference: no rounding of the MatMul's output
    model = _graph()
    before = _run(model, x)
    # The tolerance bites: with the pair, y is the rounded output (off by up to SY / 2).
    np.testing.assert_allclose(before["y"], _round(xq @ w1, SY) + BIAS, atol=1e-5)
    assert np.abs(before["y"] - exact_y).max() > 1e-3
    y2_before = before["y2"]

    assert dequantised_outputs(model, ["MatMul", "Gemm"]) == ["first"]
    after = _run(model, x)
    np.testing.assert_allclose(after["y"], exact_y, atol=1e-5)
    # The second MatMul's output is read, behind a Reshape, by a quantised MatMul: unchanged.
    np.testing.assert_array_equal(after["y2"], y2_before)
    names = {n.name for n in model.graph.node}
    assert {"q_h", "dq_h"}.isdisjoint(names) and {"q_g", "dq_g"} <= names
    assert not {"h.s", "h.z"} & {i.name for i in model.graph.initializer}  # its scale and zero point go too
    onnx.checker.check_model(model)


def test_a_pair_a_quantised_elementwise_op_reads_stays() -> None:
    """Under --int8-elementwise the quantiser's op types include Add: the first MatMul's
    output then feeds a quantised op, and its pair stays."""
    model = _graph()
    assert dequantised_outputs(model, ["MatMul"], quantised_ops=["Conv", "MatMul", "Gemm", "Add"]) == []


def test_op_types_not_named_and_graph_outputs_keep_their_pairs() -> None:
    model = _graph()
    assert dequantised_outputs(model, ["Conv"]) == [] and dequantised_outputs(model, []) == []
    assert len(model.graph.node) == len(_graph().graph.node)
    # A pair whose DequantizeLinear writes a graph output keeps it (the interface's name).
    model = _graph()
    model.graph.output.append(helper.make_tensor_value_info("h.dq", TensorProto.FLOAT, [2, 6]))
    assert dequantised_outputs(model, ["MatMul"]) == []


def test_float_outputs_option_defaults_and_errors() -> None:
    """MatMul and Gemm outputs float by default (free on ONNX Runtime), Conv too with "all"."""
    from e3dpsm.quantize import Advanced
    from e3dpsm.quantize.outputs import FLOAT_OUTPUTS

    assert QuantizeOptions().advanced.float_outputs == "matmul"
    assert FLOAT_OUTPUTS["matmul"] == ("MatMul", "Gemm") and FLOAT_OUTPUTS["none"] == ()
    assert FLOAT_OUTPUTS["all"] == ("Conv", "MatMul", "Gemm")
    with pytest.raises(ConfigError, match="--float-outputs"):
        Advanced(float_outputs="conv")
