"""`quantize --mode int8-weights` (quantize/weights.py): each Conv / Gemm / MatMul weight stored
as int8 codes and one scale per output channel, rebuilt by Cast and Mul that ONNX Runtime
folds into one float weight at load. Checked against numpy: the scales (largest |w| / 127),
the codes (within half a step), the toy graph's outputs (numpy's products with the rebuilt
weights), the folding (the optimised graph ONNX Runtime writes holds no Cast or Mul of a
weight: the step is an fp32 step), and the trained tiny end to end."""
from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.quantize.weights import output_channel_axis, symmetric_codes, weight_only_int8


def _rng():
    return np.random.default_rng(7)


@pytest.mark.parametrize("axis", [0, 1, 3])
def test_codes_and_scales_by_hand(axis) -> None:
    weight = _rng().normal(size=(4, 5, 3, 6)).astype(np.float32)
    index = [slice(None)] * 4
    index[axis] = 1
    weight[tuple(index)] = 0.0
    codes, scale = symmetric_codes(weight, axis)
    assert codes.dtype == np.int8 and scale.dtype == np.float32 and scale.shape == (weight.shape[axis],)
    moved = np.moveaxis(weight, axis, 0).reshape(weight.shape[axis], -1)
    expected = np.abs(moved).max(axis=1) / 127.0
    expected[1] = 1.0  # a channel of zeros: scale 1, codes 0
    np.testing.assert_allclose(scale, expected, rtol=1e-6)
    rebuilt = np.moveaxis(codes, axis, 0).reshape(len(scale), -1) * scale[:, None]
    assert np.all(np.abs(rebuilt - moved) <= scale[:, None] / 2 * (1 + 1e-6))
    assert np.abs(codes).max() == 127 and not np.moveaxis(codes, axis, 0)[1].any()


@pytest.mark.parametrize("op, attrs, shape, axis", [
    ("Conv", {}, (8, 3, 3, 3), 0), ("Gemm", {"transB": 1}, (8, 5), 0), ("Gemm", {}, (5, 8), 1),
    ("Gemm", {"transB": 0}, (5, 8), 1), ("MatMul", {}, (5, 8), 1), ("MatMul", {}, (2, 5, 8), 2),
    ("MatMul", {}, (8,), None)])
def test_the_output_channel_axis_of_each_op(op, attrs, shape, axis) -> None:
    node = helper.make_node(op, ["x", "w"], ["y"], **attrs)
    assert output_channel_axis(node, np.zeros(shape, np.float32)) == axis


def _toy() -> tuple[onnx.ModelProto, dict[str, np.ndarray]]:
    """x [1, 3, 4, 4] -> 1x1 Conv (6 channels, bias) -> flatten -> Gemm (transB) -> MatMul -> y,
    and a second MatMul reading the same weight as the first (one rebuild, two readers)."""
    rng = _rng()
    weights = {"conv_w": rng.normal(size=(6, 3, 1, 1)), "conv_b": rng.normal(size=6),
               "gemm_w": rng.normal(size=(10, 96)), "mm_w": rng.normal(size=(10, 7))}
    weights = {k: v.astype(np.float32) for k, v in weights.items()}
    nodes = [helper.make_node("Conv", ["x", "conv_w", "conv_b"], ["c"]),
             helper.make_node("Flatten", ["c"], ["f"]),
             helper.make_node("Gemm", ["f", "gemm_w"], ["g"], transB=1),
             helper.make_node("MatMul", ["g", "mm_w"], ["y"]),
             helper.make_node("MatMul", ["g", "mm_w"], ["z"])]
    graph = helper.make_graph(nodes, "toy", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 4, 4])],
                              [helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, 7]) for n in ("y", "z")],
                              [numpy_helper.from_array(v, k) for k, v in weights.items()])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8), weights


def _numpy_toy(x: np.ndarray, w: dict[str, np.ndarray]) -> np.ndarray:
    conv = np.einsum("oi,bihw->bohw", w["conv_w"][:, :, 0, 0], x) + w["conv_b"][None, :, None, None]
    return conv.reshape(1, -1) @ w["gemm_w"].T @ w["mm_w"]


def test_the_toy_graph_computes_numpys_products_with_the_rebuilt_weights(tmp_path) -> None:
    import onnxruntime as ort

    model, weights = _toy()
    quantised, info = weight_only_int8(model)
    assert info["weights_int8"] == 3 and info["arithmetic"] == "float"  # the shared MatMul weight once; the bias stays
    stored = {i.name: numpy_helper.to_array(i) for i in quantised.graph.initializer}
    assert {"conv_w", "gemm_w", "mm_w"}.isdisjoint(stored) and stored["conv_b"].dtype == np.float32
    assert info["weight_bytes_stored"] == sum(stored[f"{n}__int8"].nbytes + stored[f"{n}__scale"].nbytes
                                              for n in ("conv_w", "gemm_w", "mm_w"))
    rebuilt = dict(weights)
    for name, axis in (("conv_w", 0), ("gemm_w", 0), ("mm_w", 1)):
        codes, scale = symmetric_codes(weights[name], axis)
        assert np.array_equal(stored[f"{name}__int8"], codes)
        shape = [1] * codes.ndim
        shape[axis] = -1
        rebuilt[name] = codes * scale.reshape(shape)
    onnx.checker.check_model(quantised)
    x = _rng().normal(size=(1, 3, 4, 4)).astype(np.float32)
    options = ort.SessionOptions()
    options.optimized_model_filepath = str(tmp_path / "optimised.onnx")
    session = ort.InferenceSession(quantised.SerializeToString(), options, providers=["CPUExecutionProvider"])
    y, z = session.run(["y", "z"], {"x": x})
    np.testing.assert_allclose(y, _numpy_toy(x, rebuilt), rtol=1e-4, atol=1e-4)
    assert np.array_equal(y, z)
    # near the tolerance: the fp32 weights' products are measurably elsewhere
    assert np.abs(y - _numpy_toy(x, weights)).max() > 1e-3
    optimised = onnx.load(str(tmp_path / "optimised.onnx"))
    assert not [n.op_type for n in optimised.graph.node if n.op_type in ("Cast", "Mul", "DequantizeLinear")]


def test_weight_only_searches_nothing_so_its_search_split_is_free() -> None:
    """Like dynamic INT8: no search, so --search-split may be the calibration split."""
    from e3dpsm.errors import ConfigError
    from e3dpsm.quantize.options import QuantizeOptions

    QuantizeOptions(mode="int8-weights", split="train", search_split="train")
    with pytest.raises(ConfigError, match="different splits"):
        QuantizeOptions(mode="int8", split="train", search_split="train")


def test_quantize_writes_a_judged_weight_only_graph_of_the_trained_tiny(trained_graph, quant_data, tmp_path) -> None:
    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.quantize.options import QuantizeOptions
    from e3dpsm.quantize.pipeline import quantize_graph

    report = quantize_graph(trained_graph, quant_data, tmp_path / "qw", QuantizeOptions(mode="int8-weights", threads=1))
    path = tmp_path / "qw" / "step_int8_weights.onnx"
    model = onnx.load(str(path))
    meta = GraphMetadata.from_onnx(model, source=str(path))
    assert meta.quantization["mode"] == "int8-weights" and meta.quantization["arithmetic"] == "float"
    assert report["verdict"]["within_budget"] and report["verdict"]["size_ratio"] < 1.0
    assert meta.quantization["weight_bytes_stored"] < 0.3 * meta.quantization["weight_bytes_float"]
    casts = [n for n in model.graph.node if n.op_type == "Cast" and n.input[0].endswith("__int8")]
    assert len(casts) == meta.quantization["weights_int8"] > 0
    assert not [n for n in model.graph.node if n.op_type in ("QuantizeLinear", "DequantizeLinear")]


def test_a_weight_another_node_also_reads_stays_float() -> None:
    """A Gemm weight that an Add reads too (and one a subgraph reads) keeps its float tensor:
    rebuilding it would store both, so it is left alone and counted nowhere."""
    model, weights = _toy()
    graph = model.graph
    graph.node.append(helper.make_node("Add", ["gemm_w", "gemm_w"], ["doubled"]))
    then = helper.make_graph([helper.make_node("Identity", ["mm_w"], ["inner"])], "then", [],
                             [helper.make_tensor_value_info("inner", TensorProto.FLOAT, [10, 7])])
    graph.initializer.append(numpy_helper.from_array(np.array(True), "flag"))
    graph.node.append(helper.make_node("If", ["flag"], ["picked"], then_branch=then, else_branch=then))
    quantised, info = weight_only_int8(model)
    stored = {i.name for i in quantised.graph.initializer}
    assert info["weights_int8"] == 1 and {"gemm_w", "mm_w", "conv_w__int8"} <= stored and "conv_w" not in stored
    assert info["weight_bytes_float"] == weights["conv_w"].nbytes


def test_a_weight_a_weighted_node_reads_as_its_data_stays_float() -> None:
    """Where a node reads a weight counts, not only which node: `mm_w` as a MatMul's first
    input (its data) as well as the weight of two others keeps its float tensor."""
    model, _ = _toy()
    graph = model.graph
    graph.initializer.append(numpy_helper.from_array(np.ones((7, 2), np.float32), "right"))
    graph.node.append(helper.make_node("MatMul", ["mm_w", "right"], ["mm_w_right"]))
    quantised, info = weight_only_int8(model)
    stored = {i.name for i in quantised.graph.initializer}
    assert "mm_w" in stored and "mm_w__int8" not in stored
    assert {"conv_w__int8", "gemm_w__int8", "right__int8"} <= stored and info["weights_int8"] == 3


def test_a_vector_or_half_precision_weight_is_left_and_the_nodes_after_it_are_not() -> None:
    """No output-channel axis (a MatMul by a vector) or not float32: the weight stays as it is,
    and the weighted nodes after it are still rebuilt."""
    model, _ = _toy()
    graph = model.graph
    graph.initializer.extend([numpy_helper.from_array(np.ones(7, np.float32), "vector"),
                              numpy_helper.from_array(np.ones((7, 3), np.float16), "half")])
    skipped = [helper.make_node("MatMul", ["y", "vector"], ["yv"]), helper.make_node("MatMul", ["y", "half"], ["yh"])]
    nodes = skipped + list(graph.node)  # first, so every rebuilt weight's node comes after them
    del graph.node[:]
    graph.node.extend(nodes)
    quantised, info = weight_only_int8(model)
    stored = {i.name: i for i in quantised.graph.initializer}
    assert {"vector", "half"} <= set(stored) and not {"vector__int8", "half__int8"} & set(stored)
    assert stored["half"].data_type == TensorProto.FLOAT16
    assert info["weights_int8"] == 3 and {"conv_w__int8", "gemm_w__int8", "mm_w__int8"} <= set(stored)


def test_weight_only_refuses_an_exclude_list() -> None:
    from e3dpsm.errors import ConfigError
    from e3dpsm.quantize.options import QuantizeOptions

    QuantizeOptions(mode="int8-weights", exclude="none")
    with pytest.raises(ConfigError, match="--exclude head keeps nodes float .* drop --exclude"):
        QuantizeOptions(mode="int8-weights", exclude="head")


def test_an_over_budget_weight_only_graph_is_told_what_helps() -> None:
    from e3dpsm.quantize.verdict import OVER_BUDGET_FIX

    assert "--exclude" not in OVER_BUDGET_FIX["int8-weights"] and "--exclude" in OVER_BUDGET_FIX["int8"]
