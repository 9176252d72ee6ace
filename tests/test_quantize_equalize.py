"""Equalisation (quantize/equalize.py): GEGLU and LayerNorm sites. The fp32 function is
unchanged, the per-channel ranges are evened out by the SmoothQuant scales."""
from __future__ import annotations

import numpy as np
import onnx
from onnx import numpy_helper

import onnxruntime as ort
import pytest
from onnx import TensorProto, helper

from e3dpsm.errors import ConfigError
from e3dpsm.quantize.api import QuantizeOptions
from e3dpsm.quantize.equalize import (channel_maxima, equalize, equalize_geglu, equalize_layernorms,
                                      find_geglu_sites, find_layernorm_sites)


def _largest_output_gap(graph_a, graph_b, sequence, frames: int = 20) -> float:
    """The largest difference of any output (poses in mm, states) between two graphs streamed
    over the first `frames` frames of `sequence`, each carrying its own states."""
    from e3dpsm.runtime import StepSession

    a, b = StepSession(graph_a), StepSession(graph_b)
    sa, sb, worst = a.init_state(1), b.init_state(1), 0.0
    for f in range(frames):
        x = np.asarray(sequence.lnes[f: f + 1], np.float32)
        oa, sa = a.step(x, sa, 20.0)
        ob, sb = b.step(x, sb, 20.0)
        worst = max(worst, max(float(np.abs(oa[k] - ob[k]).max()) for k in oa))
    return worst


def test_equalized_graph_computes_the_same_poses(tmp_path, trained_graph, quant_data) -> None:  # noqa: F811
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize.calibration import record_calibration_set

    model = onnx.load(str(trained_graph))
    sites = find_geglu_sites(model)
    # the two S5 blocks' feed-forwards (MatMul) and the four attention blocks' (Gemm between Reshapes)
    assert len(sites) == 6 and all(s.value_columns[0] == 0 for s in sites)
    assert sorted(model_node_types(model, s.proj_in) for s in sites) == ["Gemm"] * 4 + ["MatMul"] * 2
    data = PreparedData.open(quant_data)
    calib = record_calibration_set(trained_graph, data.split("train"), 16, 20.0)
    equalized, done = equalize_geglu(model, calib.feeds)
    assert len(done) == 6
    before = channel_maxima(model, [s.product for s in sites], calib.feeds)
    after = channel_maxima(equalized, [s.product for s in sites], calib.feeds)
    for site, record in zip(sites, done):
        # s_j = sqrt(a_j / w_j): the channels' ranges a_j / s_j = sqrt(a_j w_j) are closer together
        spread = lambda m: m.max() / m[m > 0].min()  # noqa: E731
        assert spread(after[site.product]) < spread(before[site.product])
        assert abs(after[site.product].max() - record["activation_range_after"]) < 1e-4 * record["activation_range_after"]
    weights = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    changed = [i.name for i in equalized.graph.initializer
               if not np.array_equal(numpy_helper.to_array(i), weights[i.name])]
    # W_in and W_out of each site and the attention blocks' proj_in biases, nothing else
    assert len(changed) == 2 * 6 + sum(s.bias is not None for s in sites)
    onnx.save(equalized, str(tmp_path / "eq.onnx"))
    worst = _largest_output_gap(trained_graph, tmp_path / "eq.onnx", data.split("val")[0])
    assert worst < 1e-3  # mm: float32 round-off on poses of ~1,000 mm


def model_node_types(model: onnx.ModelProto, name: str) -> str:
    return next(n.op_type for n in model.graph.node if (n.name or n.output[0]) == name)


def test_a_scale_on_one_side_only_breaks_the_function(tmp_path, trained_graph) -> None:  # noqa: F811
    """The test above can fail: scaling W_out's rows without W_in's value columns moves the
    poses by far more than round-off."""
    from e3dpsm.runtime import StepSession

    model = onnx.load(str(trained_graph))
    site = find_geglu_sites(model)[1]
    node = next(n for n in model.graph.node if n.name == site.proj_out)
    init = next(i for i in model.graph.initializer if i.name == node.input[1])
    init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) * 2.0, init.name))
    onnx.save(model, str(tmp_path / "broken.onnx"))
    session_a, session_b = StepSession(trained_graph), StepSession(tmp_path / "broken.onnx")
    x = np.random.default_rng(0).random((1, 2, 192, 256), dtype=np.float32) * (np.random.default_rng(1).random(
        (1, 2, 192, 256)) < 0.05)
    oa, _ = session_a.step(x, session_a.init_state(1), 20.0)
    ob, _ = session_b.step(x, session_b.init_state(1), 20.0)
    assert np.abs(oa["pose"] - ob["pose"]).max() > 1e-2


def _layernorm_graph(shared_weight: bool = False, y_output: bool = False, square: bool = False) -> onnx.ModelProto:
    """x [2, 5, 6] -> LayerNorm(gamma, beta) -> y, read by MatMul(W1), by Reshape[-1, 6] ->
    Gemm(W2, transB=1), by a residual Add with x and by Shape. Channel 4 of gamma is 40x the
    rest, the outlier SmoothQuant migrates into the weights."""
    rng = np.random.default_rng(3)
    gamma = rng.uniform(0.5, 1.5, 6).astype(np.float32)
    gamma[4] = 40.0
    w1 = rng.normal(size=(6, 4)).astype(np.float32)
    w2 = rng.normal(size=(3, 6)).astype(np.float32)
    inits = [numpy_helper.from_array(gamma, "gamma"), numpy_helper.from_array(rng.normal(size=6).astype(np.float32), "beta"),
             numpy_helper.from_array(w1, "W1"), numpy_helper.from_array(w2, "W2"),
             numpy_helper.from_array(np.array([-1, 6], np.int64), "flat")]
    nodes = [helper.make_node("LayerNormalization", ["x", "gamma", "beta"], ["y"], name="norm", axis=-1),
             helper.make_node("MatMul", ["y", "W1"], ["a"], name="proj_a"),
             helper.make_node("Reshape", ["y", "flat"], ["y2"], name="flatten"),
             helper.make_node("Gemm", ["y2", "W2"], ["b"], name="proj_b", transB=1),
             helper.make_node("Add", ["y", "x"], ["r"], name="residual"),
             helper.make_node("Shape", ["y"], ["s"], name="shape")]
    outputs = [helper.make_tensor_value_info("a", TensorProto.FLOAT, [2, 5, 4]),
               helper.make_tensor_value_info("b", TensorProto.FLOAT, [10, 3]),
               helper.make_tensor_value_info("r", TensorProto.FLOAT, [2, 5, 6]),
               helper.make_tensor_value_info("s", TensorProto.INT64, [3])]
    if y_output:  # y itself is a graph output
        outputs.append(helper.make_tensor_value_info("y", TensorProto.FLOAT, [2, 5, 6]))
    if square:  # one node reading y in both its slots
        nodes.append(helper.make_node("Mul", ["y", "y"], ["yy"], name="square"))
        outputs.append(helper.make_tensor_value_info("yy", TensorProto.FLOAT, [2, 5, 6]))
    if shared_weight:  # a second MatMul reads W1 from another tensor
        nodes.append(helper.make_node("MatMul", ["x", "W1"], ["c"], name="other"))
        outputs.append(helper.make_tensor_value_info("c", TensorProto.FLOAT, [2, 5, 4]))
    graph = helper.make_graph(nodes, "ln", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 5, 6])],
                              outputs, inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def _run(model: onnx.ModelProto, x: np.ndarray) -> list[np.ndarray]:
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(None, {"x": x})


def test_layernorm_scales_fold_into_both_projections_and_the_residual_gets_y_back() -> None:
    model = _layernorm_graph()
    sites = find_layernorm_sites(model)
    assert len(sites) == 1
    site = sites[0]
    assert {(p.node, p.channel_axis) for p in site.projections} == {("proj_a", 0), ("proj_b", 1)}
    assert site.restored == (("residual", "y"),)  # Shape needs nothing
    rng = np.random.default_rng(0)
    feeds = [{"x": rng.normal(size=(2, 5, 6)).astype(np.float32) * 3} for _ in range(4)]
    equalized, done = equalize_layernorms(model, feeds)
    # The scales, from numpy alone: s_j = sqrt(max|y_j| / max_k |W[j, k]|) over both weights.
    def layer_norm(x: np.ndarray, g: np.ndarray, b: np.ndarray) -> np.ndarray:
        x = x.astype(np.float64)
        return (x - x.mean(-1, keepdims=True)) / np.sqrt(x.var(-1, keepdims=True) + 1e-5) * g + b
    w = {i.name: numpy_helper.to_array(i).astype(np.float64) for i in model.graph.initializer}
    act = np.max([np.abs(layer_norm(f["x"], w["gamma"], w["beta"])).reshape(-1, 6).max(0) for f in feeds], axis=0)
    wmax = np.maximum(np.abs(w["W1"]).max(1), np.abs(w["W2"]).max(0))
    scale = np.sqrt(act / wmax)
    after = {i.name: numpy_helper.to_array(i).astype(np.float64) for i in equalized.graph.initializer}
    np.testing.assert_allclose(after["gamma"], w["gamma"] / scale, rtol=1e-5)
    np.testing.assert_allclose(after["beta"], w["beta"] / scale, rtol=1e-5)
    np.testing.assert_allclose(after["W1"], w["W1"] * scale[:, None], rtol=1e-5)
    np.testing.assert_allclose(after["W2"], w["W2"] * scale[None, :], rtol=1e-5)
    assert done[0]["restored_readers"] == 1 and done[0]["projections"] == ["proj_a", "proj_b"]
    # The outlier channel's range came down to the others': the spread of y's channel ranges shrank.
    y_after = channel_maxima(equalized, ["y"], feeds)["y"]
    assert (y_after.max() / y_after.min()) < 0.5 * (act.max() / act.min())
    # Every output the same to float32 round-off; the graph is still valid and ordered.
    onnx.checker.check_model(equalized)
    x = rng.normal(size=(2, 5, 6)).astype(np.float32)
    for before_out, after_out in zip(_run(model, x), _run(equalized, x)):
        np.testing.assert_allclose(after_out, before_out, rtol=1e-5, atol=1e-5)


def test_without_the_restoring_mul_the_residual_moves() -> None:
    """The test above can fail: the residual reading the scaled y (the Mul bypassed) is off."""
    model = _layernorm_graph()
    feeds = [{"x": np.random.default_rng(1).normal(size=(2, 5, 6)).astype(np.float32)}]
    equalized, _ = equalize_layernorms(model, feeds)
    residual = next(n for n in equalized.graph.node if n.name == "residual")
    residual.input[0] = "y"
    x = np.random.default_rng(2).normal(size=(2, 5, 6)).astype(np.float32)
    (a, b, r, _), (a2, b2, r2, _) = _run(model, x), _run(equalized, x)
    np.testing.assert_allclose(a2, a, rtol=1e-5, atol=1e-5)  # the projections still see y
    np.testing.assert_allclose(b2, b, rtol=1e-5, atol=1e-5)
    assert np.abs(r2 - r).max() > 0.1


def test_a_weight_another_node_reads_or_a_graph_output_is_not_a_site() -> None:
    assert find_layernorm_sites(_layernorm_graph(shared_weight=True)) == []
    assert find_layernorm_sites(_layernorm_graph(y_output=True)) == []  # the graph would output y / s


def test_a_node_reading_y_twice_gets_one_restoring_mul() -> None:
    model = _layernorm_graph(square=True)
    site, = find_layernorm_sites(model)
    assert site.restored == (("residual", "y"), ("square", "y"))
    feeds = [{"x": np.random.default_rng(6).normal(size=(2, 5, 6)).astype(np.float32)}]
    equalized, done = equalize_layernorms(model, feeds)
    assert done[0]["restored_readers"] == 2
    square = next(n for n in equalized.graph.node if n.name == "square")
    assert square.input[0] == square.input[1] != "y"
    assert sum(n.op_type == "Mul" for n in equalized.graph.node) == 3  # square + 2 restoring
    x = np.random.default_rng(7).normal(size=(2, 5, 6)).astype(np.float32)
    for before_out, after_out in zip(_run(model, x), _run(equalized, x)):
        np.testing.assert_allclose(after_out, before_out, rtol=1e-5, atol=1e-5)


def test_layernorm_equalized_model_computes_the_same_poses(tmp_path, trained_graph, quant_data) -> None:  # noqa: F811
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize.calibration import record_calibration_set

    model = onnx.load(str(trained_graph))
    sites = find_layernorm_sites(model)
    norms = [n.name for n in model.graph.node if n.op_type == "LayerNormalization"]
    assert len(sites) >= len(norms) - 2, (len(sites), norms)  # all but norms read by no projection
    data = PreparedData.open(quant_data)
    calib = record_calibration_set(trained_graph, data.split("train"), 16, 20.0)
    equalized, done = equalize(model, calib.feeds)
    kinds = [d["kind"] for d in done]
    assert kinds.count("geglu") == 6 and kinds.count("layernorm") == len(sites)
    onnx.save(equalized, str(tmp_path / "eq.onnx"))
    worst = _largest_output_gap(trained_graph, tmp_path / "eq.onnx", data.split("val")[0])
    assert worst < 1e-3  # mm, as for the GEGLU sites alone


@pytest.mark.parametrize("options", [dict(mode="fp16", equalize=True),
                                     dict(mode="int8", equalize=True, ranges_from_checkpoint="qat.pt")])
def test_equalize_is_refused_where_it_would_mislead(options) -> None:
    with pytest.raises(ConfigError, match="--equalize"):
        QuantizeOptions(**options)


def test_a_folding_that_changes_the_function_is_refused(monkeypatch) -> None:
    """equalize() runs the folded graph against the original once: a site folded inexactly
    (here W1 doubled after the LayerNorm folding) is one clear InputError, not a silently
    different model."""
    import e3dpsm.quantize.equalize as eq
    from e3dpsm.errors import InputError

    model = _layernorm_graph()
    feeds = [{"x": np.random.default_rng(4).normal(size=(2, 5, 6)).astype(np.float32)}]
    assert len(equalize(model, feeds)[1]) == 1  # the exact folding passes the check
    folding = eq.equalize_layernorms

    def inexact(m, f, alpha=eq.ALPHA):
        folded, done = folding(m, f, alpha)
        w1 = next(i for i in folded.graph.initializer if i.name == "W1")
        w1.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(w1) * 2.0, "W1"))
        return folded, done

    monkeypatch.setattr(eq, "equalize_layernorms", inexact)
    with pytest.raises(InputError, match="--equalize changed the fp32 output 'a'"):
        equalize(model, feeds)


@pytest.mark.parametrize("bias_shape", [(6,), (1, 6)])
def test_geglu_bias_of_either_layout_takes_the_value_half_scales_only(bias_shape) -> None:
    """x @ W_in + b -> value [0:3] * sigmoid(gate [3:6]) -> @ W_out, b stored as [2H] or
    [1, 2H] (both legal for an Add): the value half of b is divided by s, the gate half left,
    the outputs unchanged. A scalar bias is no per-channel bias: no site."""
    rng = np.random.default_rng(8)
    value = rng.normal(size=(4, 6)).astype(np.float32)
    value[:, 1] *= 30.0  # one outlier value channel
    bias = rng.normal(size=bias_shape).astype(np.float32)
    w_out = rng.normal(size=(3, 4)).astype(np.float32)

    def graph(b: np.ndarray) -> onnx.ModelProto:
        inits = [numpy_helper.from_array(value, "W_in"), numpy_helper.from_array(b, "b"),
                 numpy_helper.from_array(w_out, "W_out")]
        consts = {"s0": [0], "e0": [3], "s1": [3], "e1": [6], "ax": [-1]}
        inits += [numpy_helper.from_array(np.array(v, np.int64), k) for k, v in consts.items()]
        nodes = [helper.make_node("MatMul", ["x", "W_in"], ["h"], name="proj_in"),
                 helper.make_node("Add", ["h", "b"], ["hb"], name="bias"),
                 helper.make_node("Slice", ["hb", "s0", "e0", "ax"], ["v"], name="value"),
                 helper.make_node("Slice", ["hb", "s1", "e1", "ax"], ["g"], name="gate"),
                 helper.make_node("Sigmoid", ["g"], ["sg"], name="act"),
                 helper.make_node("Mul", ["v", "sg"], ["p"], name="product"),
                 helper.make_node("MatMul", ["p", "W_out"], ["y"], name="proj_out")]
        g = helper.make_graph(nodes, "geglu", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 5, 4])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2, 5, 4])], inits)
        return helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)

    model = graph(bias)
    site, = find_geglu_sites(model)
    assert (site.proj_in, site.bias, site.proj_out, site.value_columns) == ("proj_in", "b", "proj_out", (0, 3))
    feeds = [{"x": rng.normal(size=(2, 5, 4)).astype(np.float32)} for _ in range(3)]
    equalized, done = equalize_geglu(model, feeds)
    scale = done[0]["activation_range_before"] / done[0]["activation_range_after"]
    assert scale > 1.5  # the outlier channel's range came down
    after = {i.name: numpy_helper.to_array(i) for i in equalized.graph.initializer}
    assert after["b"].shape == bias.shape
    np.testing.assert_array_equal(after["b"].reshape(-1)[3:], bias.reshape(-1)[3:])  # the gate half untouched
    assert not np.allclose(after["b"].reshape(-1)[:3], bias.reshape(-1)[:3])
    # SmoothQuant's scales written out in numpy (Xiao et al. 2023, eq. 4, alpha 1/2):
    # s_j = sqrt(max|p_j| / max_k |W_out[j, k]|), p the product over every feed.
    def product(x: np.ndarray) -> np.ndarray:
        h = x.astype(np.float64) @ value + bias.reshape(-1)
        return h[..., :3] / (1.0 + np.exp(-h[..., 3:]))
    p_max = np.max([np.abs(product(f["x"])).reshape(-1, 3).max(axis=0) for f in feeds], axis=0)
    s = np.sqrt(p_max / np.abs(w_out).max(axis=1))
    np.testing.assert_allclose(after["W_in"][:, :3], value[:, :3] / s, rtol=1e-5)
    np.testing.assert_array_equal(after["W_in"][:, 3:], value[:, 3:])
    np.testing.assert_allclose(after["W_out"], w_out * s[:, None], rtol=1e-5)
    np.testing.assert_allclose(after["b"].reshape(-1)[:3], bias.reshape(-1)[:3] / s, rtol=1e-5)
    x = feeds[0]["x"]
    np.testing.assert_allclose(_run(equalized, x)[0], _run(model, x)[0], rtol=1e-5, atol=1e-5)
    assert find_geglu_sites(graph(np.float32(0.5).reshape(()))) == []
