"""The portable INT8 form (e3dpsm/golden/kernel_cut.py `portable_qdq`, `python -m
e3dpsm.golden.kernel_report portable`): which quantised activations stay 8-bit, the Q/DQ pairs
removed, the rounds it takes, and what the graph then computes, against numpy."""
from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.golden.kernel_cut import (BOOKKEEPING_OPS, EXACT_FLOAT_OPS, FEED_SUFFIX, cut_at_quantized,
                                      drop_quantization, expose_quantized, portable_qdq, portable_segment,
                                      quantized_activations, segment_ops)

SCALES = {"x": (0.05, 128), "s": (1 / 255, 0), "a": (2 / 255, 0), "m": (0.1, 128), "k": (0.1, 128)}
RNG = np.random.default_rng(0)
W = RNG.integers(-127, 128, (6, 4)).astype(np.int8)  # the MatMul weights' codes, scale 0.02
W2 = RNG.integers(-127, 128, (6, 3)).astype(np.int8)


def _q(name: str, source: str) -> list[onnx.NodeProto]:
    """source -> QuantizeLinear -> {name}_q (the code)."""
    return [helper.make_node("QuantizeLinear", [source, f"s_{name}", f"z_{name}"], [f"{name}_q"], name=f"q_{name}")]


def _dq(name: str, out: str) -> onnx.NodeProto:
    return helper.make_node("DequantizeLinear", [f"{name}_q", f"s_{name}", f"z_{name}"], [out], name=f"dq_{out}")


def _graph() -> onnx.ModelProto:
    """x -Q/DQ-> Sigmoid -Q-> s_q, read by two DQs -> Add -Q/DQ-> MatMul -Q/DQ-> y; and beside it
    x's DQ -> MatMul -Q/DQ-> z (an integer segment that depends on nothing non-portable)."""
    inits = []
    for name, (scale, zero) in SCALES.items():
        inits += [numpy_helper.from_array(np.array(scale, np.float32), f"s_{name}"),
                  numpy_helper.from_array(np.array(zero, np.uint8), f"z_{name}")]
    for name, codes in (("w", W), ("w2", W2)):
        inits += [numpy_helper.from_array(codes, f"{name}_q"), numpy_helper.from_array(np.array(0.02, np.float32), f"s_{name}"),
                  numpy_helper.from_array(np.array(0, np.int8), f"z_{name}")]
    nodes = [*_q("x", "x"), _dq("x", "x_dq"),
             helper.make_node("Sigmoid", ["x_dq"], ["sig"], name="sigmoid"), *_q("s", "sig"),
             _dq("s", "s_dq1"), _dq("s", "s_dq2"),
             helper.make_node("Add", ["s_dq1", "s_dq2"], ["added"], name="add"), *_q("a", "added"), _dq("a", "a_dq"),
             _dq("w", "w"), helper.make_node("MatMul", ["a_dq", "w"], ["mm"], name="matmul"), *_q("m", "mm"),
             _dq("m", "y"),
             _dq("w2", "w2"), helper.make_node("MatMul", ["x_dq", "w2"], ["mm2"], name="matmul2"), *_q("k", "mm2"),
             _dq("k", "z")]
    graph = helper.make_graph(nodes, "portable", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 6])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2, 4]),
                               helper.make_tensor_value_info("z", TensorProto.FLOAT, [2, 3])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    onnx.checker.check_model(model)
    return model


def _quantize(name: str, value: np.ndarray) -> np.ndarray:
    """ONNX QuantizeLinear to u8 then DequantizeLinear: round half to even, saturate."""
    scale, zero = SCALES[name]
    codes = np.clip(np.rint(value / np.float32(scale)) + zero, 0, 255)
    return ((codes - zero) * np.float32(scale)).astype(np.float32)


def _run(model: onnx.ModelProto, x: np.ndarray) -> list[np.ndarray]:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL  # the graph as written
    return ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"]).run(
        ["y", "z"], {"x": x})


def test_portable_segments_are_integer_kernels_and_exact_float_ops() -> None:
    assert portable_segment([]) and portable_segment(["Conv"]) and portable_segment(["MatMul", "Add", "Relu"])
    assert portable_segment(["Gemm", "Mul", "Div", "MaxPool"])
    for inexact in ("Sigmoid", "LayerNormalization", "Softmax", "BatchNormalization", "Erf", "Exp", "GridSample"):
        assert not portable_segment(["Conv", inexact]) and inexact not in EXACT_FLOAT_OPS
    assert portable_segment(["Conv", "Sigmoid"], allowed=frozenset({"Sigmoid"}))
    assert not portable_segment(["Add"], allowed=frozenset())


def test_segments_of_the_graph() -> None:
    segments = segment_ops(_graph())
    assert segments == {"x_q": [], "s_q": ["Sigmoid"], "a_q": ["Add"], "m_q": ["MatMul"], "k_q": ["MatMul"]}


def test_dropping_a_code_read_by_two_dequantizers() -> None:
    """Both DequantizeLinear readers of s_q go with its QuantizeLinear; their readers read the
    float tensor; the count is of QuantizeLinear nodes (1), not of nodes removed (3)."""
    model = _graph()
    before = len(model.graph.node)
    assert drop_quantization(model, {"s_q"}) == 1
    assert len(model.graph.node) == before - 3
    (add,) = [n for n in model.graph.node if n.name == "add"]
    assert list(add.input) == ["sig", "sig"]
    assert "s_q" not in quantized_activations(model)


def test_a_code_that_leaves_the_graph_or_feeds_another_op_is_kept() -> None:
    model = _graph()
    model.graph.output.append(onnx.ValueInfoProto(name="s_q"))
    assert drop_quantization(model, {"s_q"}) == 0 and "s_q" in quantized_activations(model)
    model = _graph()
    model.graph.node.append(helper.make_node("Cast", ["a_q"], ["a_cast"], to=TensorProto.FLOAT))
    before = [n.name for n in model.graph.node]
    assert drop_quantization(model, {"a_q"}) == 0 and [n.name for n in model.graph.node] == before
    assert drop_quantization(model, {"no_such_code"}) == 0


def test_portable_qdq_repeats_until_every_remaining_segment_is_portable() -> None:
    """Round 1 drops s_q (Sigmoid); a_q's segment then reaches back through the Sigmoid and goes
    in round 2; m_q's then reaches through the Add and Sigmoid and goes in round 3. k_q's MatMul
    reads x's codes alone and stays, as does x_q. The weights stay 8-bit; the dropped codes'
    scales and zero points go."""
    model = _graph()
    portable, removed = portable_qdq(model)
    assert removed == ["s_q", "a_q", "m_q"]
    assert quantized_activations(portable) == ["x_q", "k_q"]
    assert segment_ops(portable) == {"x_q": [], "k_q": ["MatMul"]}
    initializers = {i.name: i.data_type for i in portable.graph.initializer}
    assert initializers["w_q"] == initializers["w2_q"] == TensorProto.INT8
    assert not {"s_s", "z_s", "s_a", "z_a", "s_m", "z_m"} & set(initializers)
    assert {"s_x", "z_x", "s_k", "z_k"} <= set(initializers)
    assert quantized_activations(model) == ["x_q", "s_q", "a_q", "m_q", "k_q"]  # the input is left as it was
    assert [o.name for o in portable.graph.output] == ["mm", "z"]  # y's DQ went; the float tensor is the output
    onnx.checker.check_model(portable)


def test_the_portable_graph_computes_the_float_segments_in_float() -> None:
    """Against numpy: y = 2 sigmoid(dq(x)) @ dq(w), no rounding in between; z keeps both codes."""
    x = np.random.default_rng(3).normal(size=(2, 6)).astype(np.float32)
    portable, _ = portable_qdq(_graph())
    portable.graph.output[0].name = "y"
    for node in portable.graph.node:
        node.output[:] = ["y" if o == "mm" else o for o in node.output]
    y, z = _run(portable, x)
    x_dq = _quantize("x", x)
    sig = (1 / (1 + np.exp(-x_dq.astype(np.float64)))).astype(np.float32)
    np.testing.assert_allclose(y, (2 * sig) @ (W.astype(np.float32) * np.float32(0.02)), rtol=0, atol=1e-5)
    np.testing.assert_allclose(z, _quantize("k", x_dq @ (W2.astype(np.float32) * np.float32(0.02))), rtol=0, atol=1e-6)
    y_int8, _ = _run(_graph(), x)
    assert np.abs(y_int8 - y).max() > 1e-3  # the original rounds s, a and m: the form changed what it computes


def test_cut_inputs_take_the_zero_points_element_type() -> None:
    """A code quantised with an int8 zero point is fed as int8 to the cut graph; u8 otherwise."""
    model = _graph()
    for init in model.graph.initializer:
        if init.name == "z_k":
            init.CopyFrom(numpy_helper.from_array(np.array(0, np.int8), "z_k"))
    model.graph.node.append(helper.make_node("Relu", ["k_q"], ["k_relu"]))
    cut, _ = cut_at_quantized(model)
    types = {i.name: i.type.tensor_type.elem_type for i in cut.graph.input}
    assert types["k_q" + FEED_SUFFIX] == TensorProto.INT8 and types["s_q" + FEED_SUFFIX] == TensorProto.UINT8


def test_the_portable_command_writes_the_form_and_says_so_in_its_metadata(tmp_path, capsys) -> None:
    from e3dpsm.golden.kernel_report import main

    model = _graph()
    model.metadata_props.add(key="e3dpsm.quantization", value=json.dumps({"mode": "int8"}))
    source, out = tmp_path / "step_int8.onnx", tmp_path / "step_int8_arm.onnx"
    onnx.save(model, str(source))
    assert main(["portable", str(source), str(out)]) == 0
    assert capsys.readouterr().out.strip() == (
        f"portable: 2 activations kept 8-bit, 3 back to float, weights 8-bit -> {out}")
    written = onnx.load(str(out))
    meta = {p.key: p.value for p in written.metadata_props}
    assert json.loads(meta["e3dpsm.quantization"]) == {
        "mode": "int8", "arm_portable": {"activations_float": 3, "activations_int8": 2}}
    assert quantized_activations(written) == ["x_q", "k_q"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["step_int8.onnx", "step_int8_arm.onnx"]


@pytest.mark.parametrize("damaged", ["not onnx", "", "float"])
def test_the_portable_command_refuses_what_is_not_a_qdq_graph(tmp_path, capsys, damaged) -> None:
    """Damaged bytes, an empty file, a float graph: one line, exit 2, nothing written."""
    from e3dpsm.golden.kernel_report import main

    source, out = tmp_path / "bad.onnx", tmp_path / "out.onnx"
    if damaged == "float":
        model = _graph()
        kept = [n for n in model.graph.node if n.op_type != "QuantizeLinear" or n.input[0] == "w_q"]
        del model.graph.node[:]
        model.graph.node.extend(kept)
        onnx.save(model, str(source))
    else:
        source.write_text(damaged)
    assert main(["portable", str(source), str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("python -m e3dpsm.golden.kernel_report portable: error: ")
    assert ("not a QDQ graph" if damaged in ("float", "") else f"{source} is not a readable ONNX file: ") in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.onnx"]


def _one_op_segment(op_type: str, inputs: int = 1) -> onnx.ModelProto:
    """x -Q/DQ-> op -> Q: the op's segment (the graph is read, not run). A Constant, which reads
    nothing, goes in through a Concat."""
    model = _graph()
    if op_type == "Constant":
        middle = [helper.make_node("Constant", [], ["c"], value=numpy_helper.from_array(np.ones(3, np.float32))),
                  helper.make_node("Concat", ["x_dq", "c"], ["t"], axis=0)]
    else:
        middle = [helper.make_node(op_type, ["x_dq"] * inputs, ["t"])]
    nodes = [*_q("x", "x"), _dq("x", "x_dq"), *middle, *_q("m", "t")]
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    return model


BOOKKEEPING = ("QuantizeLinear", "DequantizeLinear", "Shape", "Constant", "ConstantOfShape", "Identity", "Reshape",
               "Unsqueeze", "Squeeze", "Transpose", "Gather", "Concat", "Slice")


@pytest.mark.parametrize("op_type", BOOKKEEPING)
def test_shape_bookkeeping_is_left_out_of_a_segment(op_type) -> None:
    """Moving, selecting or describing values computes nothing a kernel could round: a segment
    of such ops alone is described as empty (and stays portable)."""
    assert segment_ops(_one_op_segment(op_type))["m_q"] == []
    assert set(BOOKKEEPING) == BOOKKEEPING_OPS


@pytest.mark.parametrize("op_type", ["Sigmoid", "Conv", "LayerNormalization", "Add"])
def test_computing_ops_are_described(op_type) -> None:
    assert segment_ops(_one_op_segment(op_type))["m_q"] == [op_type]


def _exact_case(op_type: str, rng: np.random.Generator) -> tuple[onnx.NodeProto, list[np.ndarray], np.ndarray,
                                                                  list[onnx.TensorProto]]:
    """(node, its inputs, numpy's IEEE float32 result, initializers) for each exact op."""
    a, b = (rng.normal(size=(1, 2, 6, 6)).astype(np.float32) * 3 for _ in range(2))
    b[b == 0] = 1.0
    unary = {"Relu": lambda x: np.maximum(x, np.float32(0)), "Neg": np.negative, "Abs": np.abs}
    binary = {"Add": np.add, "Sub": np.subtract, "Mul": np.multiply, "Div": np.divide, "Max": np.maximum,
              "Min": np.minimum}
    if op_type in unary:
        return helper.make_node(op_type, ["a"], ["y"]), [a], unary[op_type](a), []
    if op_type in binary:
        return helper.make_node(op_type, ["a", "b"], ["y"]), [a, b], binary[op_type](a, b), []
    if op_type == "Where":
        mask = a > 0
        return helper.make_node("Where", ["mask", "a", "b"], ["y"]), [a, b], np.where(mask, a, b), [
            numpy_helper.from_array(mask, "mask")]
    if op_type == "Equal":
        return helper.make_node("Equal", ["a", "b"], ["y"]), [a, np.where(a > 0, a, b)], a == np.where(a > 0, a, b), []
    if op_type == "Expand":
        row = a[:, :1]
        return helper.make_node("Expand", ["a", "shape"], ["y"]), [row], np.broadcast_to(row, (1, 2, 6, 6)), [
            numpy_helper.from_array(np.array([1, 2, 6, 6], np.int64), "shape")]
    if op_type == "Tile":
        return helper.make_node("Tile", ["a", "reps"], ["y"]), [a], np.tile(a, (1, 1, 2, 3)), [
            numpy_helper.from_array(np.array([1, 1, 2, 3], np.int64), "reps")]
    if op_type == "Pad":
        return helper.make_node("Pad", ["a", "pads"], ["y"]), [a], np.pad(a, ((0, 0), (0, 0), (1, 2), (2, 1))), [
            numpy_helper.from_array(np.array([0, 0, 1, 2, 0, 0, 2, 1], np.int64), "pads")]
    if op_type == "MaxPool":
        pooled = a.reshape(1, 2, 3, 2, 3, 2).max(axis=(3, 5))
        return helper.make_node("MaxPool", ["a"], ["y"], kernel_shape=[2, 2], strides=[2, 2]), [a], pooled, []
    raise AssertionError(f"no numpy reference for {op_type}: say why it is exact, or leave it out")


@pytest.mark.parametrize("op_type", sorted(EXACT_FLOAT_OPS))
def test_ops_called_exact_compute_numpys_ieee_result_to_the_bit(op_type) -> None:
    """What makes a float segment portable: each op is one IEEE operation per element (or moves
    values), so ONNX Runtime's result is numpy's float32 result bit for bit, on any ISA."""
    import onnxruntime as ort

    node, arrays, expected, inits = _exact_case(op_type, np.random.default_rng(5))
    names = ["a", "b"][: len(arrays)]
    graph = helper.make_graph([node], op_type, [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in names],
                              [onnx.ValueInfoProto(name="y")], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    (got,) = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(
        ["y"], dict(zip(names, arrays)))
    assert got.dtype == expected.dtype and got.shape == expected.shape
    assert np.array_equal(got.view(np.uint8), np.ascontiguousarray(expected).view(np.uint8))


def test_constants_quantised_are_not_activations() -> None:
    """A QuantizeLinear of an initializer or of a Constant node's output quantises a weight."""
    model = _graph()
    model.graph.initializer.extend([numpy_helper.from_array(np.ones((6, 4), np.float32), "w_float"),
                                    numpy_helper.from_array(np.ones(4, np.float32), "b_float")])
    model.graph.node.extend([*_q("m", "w_float"),
                             helper.make_node("Constant", [], ["c"], value=numpy_helper.from_array(np.ones(3, np.float32))),
                             helper.make_node("QuantizeLinear", ["c", "s_k"], ["c_q"])])
    assert quantized_activations(model) == ["x_q", "s_q", "a_q", "m_q", "k_q"]


def test_a_code_without_a_zero_point_is_fed_as_uint8() -> None:
    model = _graph()
    model.graph.node.extend([helper.make_node("QuantizeLinear", ["mm2", "s_k"], ["u_q"]),
                             helper.make_node("Relu", ["u_q"], ["u_relu"])])
    cut, names = cut_at_quantized(model)
    assert "u_q" in names
    types = {i.name: i.type.tensor_type.elem_type for i in cut.graph.input}
    assert types["u_q" + FEED_SUFFIX] == TensorProto.UINT8


def test_a_segment_reached_twice_is_walked_whole() -> None:
    """Sum(Sigmoid(x), Relu(x), Abs(Relu(x))): Relu is met twice on the walk; Sigmoid, met
    after it, is still part of the segment."""
    model = _graph()
    nodes = [*_q("x", "x"), _dq("x", "x_dq"), helper.make_node("Sigmoid", ["x_dq"], ["e"]),
             helper.make_node("Relu", ["x_dq"], ["r"]), helper.make_node("Abs", ["r"], ["b"]),
             helper.make_node("Sum", ["e", "r", "b"], ["t"]), *_q("m", "t")]
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    assert segment_ops(model)["m_q"] == ["Sigmoid", "Relu", "Abs", "Sum"]


def test_expose_says_what_a_float_graph_lacks() -> None:
    model = _graph()
    kept = [n for n in model.graph.node if n.op_type != "QuantizeLinear"]
    del model.graph.node[:]
    model.graph.node.extend(kept)
    with pytest.raises(ValueError, match="^the graph has no QuantizeLinear on a computed tensor: not a QDQ graph$"):
        expose_quantized(model)


@pytest.mark.parametrize("op_type", ["MatMul", "Conv", "Gemm"])
def test_an_integer_op_on_a_float_tensor_is_a_float_kernel(op_type) -> None:
    """x's codes dequantised, added to themselves (exact), then the op: ONNX Runtime cannot fuse
    it into an integer kernel (its input is no DequantizeLinear's), so it accumulates in float,
    in an order each ISA's kernel chooses. Described as such, and not portable; the same op
    reading the dequantised codes directly is an integer kernel. A float graph input, or a float
    weight or bias (an initializer or a Constant node's), makes it a float kernel too."""
    model = _graph()
    nodes = [*_q("x", "x"), _dq("x", "x_dq"), _dq("w", "w"), helper.make_node("Add", ["x_dq", "x_dq"], ["doubled"]),
             helper.make_node(op_type, ["doubled", "w"], ["t"]), *_q("m", "t"),
             helper.make_node(op_type, ["x_dq", "w"], ["t2"]), *_q("k", "t2"),
             helper.make_node(op_type, ["x", "w"], ["t3"]), helper.make_node("QuantizeLinear", ["t3", "s_k"], ["t3_q"]),
             helper.make_node("Constant", [], ["w_const"], value=numpy_helper.from_array(np.ones((6, 4), np.float32))),
             helper.make_node(op_type, ["x_dq", "w_const"], ["t4"]), helper.make_node("QuantizeLinear", ["t4", "s_k"], ["t4_q"]),
             helper.make_node(op_type, ["x_dq", "w_float"], ["t5"]), helper.make_node("QuantizeLinear", ["t5", "s_k"], ["t5_q"]),
             helper.make_node(op_type, ["x_dq", "w", "b_float"], ["t6"]),
             helper.make_node("QuantizeLinear", ["t6", "s_k"], ["t6_q"])]
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    model.graph.initializer.extend([numpy_helper.from_array(np.ones((6, 4), np.float32), "w_float"),
                                    numpy_helper.from_array(np.ones(4, np.float32), "b_float")])
    segments = segment_ops(model)
    assert segments["t4_q"] == segments["t5_q"] == [f"{op_type} (float)"]  # float weights: a float kernel
    assert segments["t6_q"] == [f"{op_type} (float)"]  # a float bias: not what the quantizer writes, not fused
    assert segments["m_q"] == ["Add", f"{op_type} (float)"] and not portable_segment(segments["m_q"])
    assert segments["k_q"] == [op_type] and portable_segment(segments["k_q"])
    assert segments["t3_q"] == [f"{op_type} (float)"]
    portable, removed = portable_qdq(model)
    assert sorted(removed) == ["m_q", "t3_q", "t4_q", "t5_q", "t6_q"] and quantized_activations(portable) == ["x_q", "k_q"]


def test_the_shared_onnx_read_says_what_is_wrong_in_one_line(tmp_path, monkeypatch) -> None:
    """`e3dpsm.onnx_graph.read_onnx` (quantize's source, the OpenVINO IR's graph, this command):
    a missing file, and a parser error without text, each one line naming the file."""
    from e3dpsm.errors import DataError
    from e3dpsm.onnx_graph import read_onnx

    with pytest.raises(DataError, match=rf"^model {tmp_path / 'absent.onnx'} does not exist$"):
        read_onnx(tmp_path / "absent.onnx")
    (tmp_path / "g.onnx").write_bytes(b"\x08")

    def silent(*args, **kwargs):
        raise ValueError()

    monkeypatch.setattr(onnx, "load", silent)
    with pytest.raises(DataError, match=rf"^{tmp_path / 'g.onnx'} is not a readable ONNX file: ValueError$"):
        read_onnx(tmp_path / "g.onnx")


@pytest.mark.parametrize("argv", [["quantize", "--model", "{bad}", "--mode", "fp16", "--data", "{data}", "--out", "{out}"],
                                  ["convert", "openvino", "--model", "{bad}", "--out", "{out}"]])
def test_commands_on_a_damaged_graph_say_so_through_the_shared_read(tmp_path, capsys, argv) -> None:
    """`e3dpsm quantize` and `e3dpsm convert openvino` read their graph with `read_onnx`: one line,
    exit 2, nothing written."""
    from e3dpsm.cli import main

    bad, out, data = tmp_path / "bad.onnx", tmp_path / "out", tmp_path / "data"
    bad.write_bytes(b"not onnx")
    data.mkdir()
    assert main([a.format(bad=bad, data=data, out=out) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bad} is not a readable ONNX file: " in err
    assert not out.exists()
