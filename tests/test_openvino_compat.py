"""export/openvino_compat.py: the Reshapes OpenVINO's low precision transformations misread
after an 8-bit 2-D product (a compile error, or silently wrong scales), guarded so that
OpenVINO compiles the graph and computes what ONNX Runtime and numpy compute."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from _quantize_helpers import fast, quant_data  # noqa: F401 (fixture)
from e3dpsm.export.openvino_compat import GUARD_SUFFIX, openvino_compatible, remove_guards, row_splitting_reshapes

X_SCALE, X_ZERO = np.float32(0.02), np.uint8(128)
ATTENTION = [-1, 48, 64, 4, 8]  # `paper`'s value projection at 192 x 256: 48 rows of 32 channels
SILENT = [-1, 32, 16]  # 32 is a multiple of the 16 channels: compiles, wrong scales


def _gemm_reshape(c_in: int, c_out: int, target: list[int] | str, rows: int | str | None = "rows", *,
                  per_channel: bool = True, dequantized_input: bool = True, op: str = "Gemm",
                  constant_node: bool = False, extra_reshape: list[int] | None = None, trans_b: bool = True,
                  bias: bool = False, allowzero: bool = False, weights_input: bool = False,
                  reshape_of_input_first: bool = False) -> onnx.ModelProto:
    """x [rows, c_in] -> Q/DQ (u8, per tensor) -> Gemm / MatMul with DQ(int8 W, per-channel
    scales), no bias -> Reshape(target); `target="input"` reads the shape from a graph input.
    `rows=None`: x of unknown shape; `trans_b=False`: a Gemm on W [c_in, c_out] without
    transB; `bias`: a float bias, the Gemm's third input; `weights_input`: the 8-bit weights
    are a graph input, not a constant; `reshape_of_input_first`: a Reshape of x itself comes
    first in the node list."""
    rng = np.random.default_rng(0)
    weights = rng.integers(-127, 128, size=(c_out, c_in), dtype=np.int8)
    scales = rng.uniform(0.005, 0.02, size=c_out if per_channel else ()).astype(np.float32)
    stored = weights if op == "Gemm" and trans_b else weights.T.copy()
    inits = [numpy_helper.from_array(scales, "ws"),
             numpy_helper.from_array(np.zeros(scales.shape, np.int8), "wz"),
             numpy_helper.from_array(X_SCALE, "xs"), numpy_helper.from_array(X_ZERO, "xz")]
    if not weights_input:
        inits.append(numpy_helper.from_array(stored, "w"))
    nodes = []
    if reshape_of_input_first:
        inits.append(numpy_helper.from_array(np.array([-1, 4 * c_in], np.int64), "first_shape"))
        nodes.append(helper.make_node("Reshape", ["x", "first_shape"], ["x_rows"], name="first"))
    weight_axis = 0 if op == "Gemm" and trans_b else 1
    nodes.append(helper.make_node("DequantizeLinear", ["w", "ws", "wz"], ["wd"], axis=weight_axis))
    if dequantized_input:
        nodes += [helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["xq"]),
                  helper.make_node("DequantizeLinear", ["xq", "xs", "xz"], ["xd"])]
    product_input = "xd" if dequantized_input else "x"
    if op == "Gemm":
        if bias:
            inits.append(numpy_helper.from_array(rng.uniform(-1, 1, c_out).astype(np.float32), "b"))
        nodes.append(helper.make_node("Gemm", [product_input, "wd", *(["b"] if bias else [])], ["y"],
                                      **({"transB": 1} if trans_b else {})))
    else:
        nodes.append(helper.make_node("MatMul", [product_input, "wd"], ["y"]))
    inputs = [helper.make_tensor_value_info("x", TensorProto.FLOAT, None if rows is None else [rows, c_in])]
    if weights_input:
        inputs.append(helper.make_tensor_value_info("w", TensorProto.INT8, list(stored.shape)))
    if target == "input":
        inputs.append(helper.make_tensor_value_info("shape", TensorProto.INT64, [3]))
    elif constant_node:
        nodes.append(helper.make_node("Constant", [], ["shape"], value=numpy_helper.from_array(np.array(target))))
    else:
        inits.append(numpy_helper.from_array(np.array(target, np.int64), "shape"))
    outputs = [("out", 3 if target == "input" else len(target))] + ([("x_rows", 2)] if reshape_of_input_first else [])
    nodes.append(helper.make_node("Reshape", ["y", "shape"], ["out"], name="split", **({"allowzero": 1} if allowzero else {})))
    if extra_reshape is not None:  # a second Reshape of the same product
        inits.append(numpy_helper.from_array(np.array(extra_reshape, np.int64), "shape2"))
        nodes.append(helper.make_node("Reshape", ["y", "shape2"], ["out2"], name="split2"))
        outputs.append(("out2", len(extra_reshape)))
    graph = helper.make_graph(nodes, "gemm_reshape", inputs, [
        helper.make_tensor_value_info(name, TensorProto.FLOAT, [None] * rank) for name, rank in outputs], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if rows is not None:  # the checker wants a shape on every graph input
        onnx.checker.check_model(model)
    return model


def _on_grid(rows: int, columns: int) -> np.ndarray:
    """Inputs 0.2-0.8 of a step from any rounding tie, so every runtime quantises them alike."""
    rng = np.random.default_rng(1)
    steps = rng.integers(-100, 100, size=(rows, columns)) + rng.uniform(-0.3, 0.3, size=(rows, columns))
    return (steps * X_SCALE).astype(np.float32)


def _numpy_reference(model: onnx.ModelProto, x: np.ndarray, target: list[int]) -> np.ndarray:
    """What the minimal graph computes, written out: quantise, dequantise, multiply, reshape."""
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    xq = np.clip(np.rint(x / X_SCALE) + int(X_ZERO), 0, 255)
    xd = (xq - int(X_ZERO)) * np.float64(X_SCALE)
    wd = inits["w"].astype(np.float64) * inits["ws"].astype(np.float64)[:, None]  # [c_out, c_in]
    return (xd @ wd.T).reshape(target)


def _onnx_runtime(model: onnx.ModelProto, x: np.ndarray) -> np.ndarray:
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(["out"], {"x": x})[0]


def _guarded(model: onnx.ModelProto) -> tuple[onnx.ModelProto, list[str]]:
    copy = onnx.ModelProto()
    copy.CopyFrom(model)
    guarded = openvino_compatible(copy)
    if all(i.type.tensor_type.HasField("shape") for i in copy.graph.input):  # the checker wants shapes
        onnx.checker.check_model(copy)
    return copy, guarded


@pytest.mark.parametrize("target, copies", [(ATTENTION, False), (SILENT, False), ([-1, 0, 4], True)])
def test_the_guard_leaves_onnx_runtimes_outputs_bitwise_unchanged(target, copies):
    """A Reshape moves no value: ONNX Runtime computes the same bits with the guard, and both
    equal the graph's arithmetic written in numpy. The third shape's 0 copies the product's
    channels: the guard must write it out, or the 0 would copy the guard's rows instead."""
    c_out = 32 if target != SILENT else 16
    model = _gemm_reshape(16, c_out, target)
    resolved = [c_out if v == 0 else v for v in target]
    x = _on_grid(2 * abs(int(np.prod(resolved))) // c_out, 16)
    guarded, names = _guarded(model)
    assert names == ["split"]
    assert [s.copies for s in row_splitting_reshapes(model)] == [copies]
    before, after = _onnx_runtime(model, x), _onnx_runtime(guarded, x)
    assert after.shape == before.shape and np.array_equal(after, before)
    reference = _numpy_reference(model, x, resolved)
    np.testing.assert_allclose(after, reference, rtol=1e-5, atol=1e-5 * np.abs(reference).max())


def _row_split_cases() -> list:
    """(graph, guarded?) pairs: exactly the Reshapes that split the rows of a dequantised
    2-D product with dynamic rows, to a new second axis of at least the channel count."""
    return [
        pytest.param(_gemm_reshape(16, 32, ATTENTION), True, id="paper-attention"),
        pytest.param(_gemm_reshape(16, 16, SILENT), True, id="multiple-of-channels"),
        pytest.param(_gemm_reshape(16, 3, [-1, 16, 3]), True, id="pose-head"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, op="MatMul"), True, id="2d-matmul"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, constant_node=True), True, id="constant-node-shape"),
        pytest.param(_gemm_reshape(16, 64, [-1, 16, 64]), False, id="second-axis-below-channels"),
        pytest.param(_gemm_reshape(16, 32, [-1, 32, 1]), False, id="rows-kept"),
        pytest.param(_gemm_reshape(16, 32, [0, 4, 8]), False, id="rows-copied"),
        pytest.param(_gemm_reshape(16, 32, [2, 48, 64, 4, 8]), False, id="static-first-axis"),
        pytest.param(_gemm_reshape(16, 32, [-1, 48, 64, 4, 8], rows=2 * 3072), False, id="static-rows"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, per_channel=False), False, id="per-tensor-weights"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, dequantized_input=False), False, id="float-activations"),
        pytest.param(_gemm_reshape(16, 32, "input"), False, id="shape-not-constant"),
        pytest.param(_three_d_matmul(), False, id="3d-matmul"),
        pytest.param(_gemm_reshape(16, 2, [-1, 4, 2]), True, id="two-channels"),
        pytest.param(_gemm_reshape(16, 3, [-1, 6]), True, id="two-axis-target"),
        pytest.param(_gemm_reshape(16, 24, [-1, 32, 16], trans_b=False), True, id="gemm-without-transB"),
        # W [16, 24] without transB: 24 channels, so a second axis of 20 is below them (not 16).
        pytest.param(_gemm_reshape(16, 24, [-1, 20, 24], trans_b=False), False, id="gemm-without-transB-below"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, bias=True), True, id="gemm-with-bias"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, rows=None), True, id="gemm-of-unknown-shape"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, rows=None, op="MatMul"), False, id="matmul-of-unknown-shape"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, reshape_of_input_first=True), True, id="after-another-reshape"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, allowzero=True), False, id="allowzero"),
        pytest.param(_gemm_reshape(16, 32, ATTENTION, weights_input=True), False, id="weights-not-constant"),
        pytest.param(_product_read_by_an_add(), False, id="not-a-reshape"),
    ]


def _product_read_by_an_add() -> onnx.ModelProto:
    """An Add of the product and a constant that reads like a row-splitting shape: only
    Reshapes count. (Shape inference fails on its types; the search reads no shape there.)"""
    model = _gemm_reshape(16, 32, ATTENTION)
    for node in model.graph.node:
        if node.name == "split":
            node.op_type = "Add"
    return model


def _three_d_matmul() -> onnx.ModelProto:
    """[batch, tokens, C] @ W: the channels are the last of three axes; LPT refuses that itself."""
    model = _gemm_reshape(16, 32, ATTENTION, op="MatMul")
    model.graph.input[0].CopyFrom(helper.make_tensor_value_info("x", TensorProto.FLOAT, ["batch", 3072, 16]))
    return model


@pytest.mark.parametrize("model, guarded", _row_split_cases())
def test_only_row_splitting_reshapes_are_guarded(model, guarded):
    guarded_model, names = _guarded(model)
    assert names == (["split"] if guarded else [])
    assert (f"split{GUARD_SUFFIX}" in {n.name for n in guarded_model.graph.node}) == guarded


def test_the_guard_keeps_an_odd_number_of_rows():
    """[rows, C] -> [1, -1, C] holds any row count: 5 rows of 3 channels split as [-1, 5, 3]."""
    model = _gemm_reshape(16, 3, [-1, 5, 3])
    guarded, names = _guarded(model)
    assert names == ["split"]
    x = _on_grid(5, 16)
    np.testing.assert_array_equal(_onnx_runtime(guarded, x), _onnx_runtime(model, x))
    split = row_splitting_reshapes(model)[0]
    assert (split.channels, split.target, split.copies) == (3, (-1, 5, 3), False)
    with pytest.raises(dataclasses.FrozenInstanceError):
        split.channels = 4


def test_two_reshapes_of_one_product_each_get_a_guard_and_a_second_pass_adds_none():
    model = _gemm_reshape(16, 32, ATTENTION, extra_reshape=[-1, 64, 48, 32])
    guarded, names = _guarded(model)
    assert sorted(names) == ["split", "split2"]
    assert openvino_compatible(guarded) == []
    assert len(guarded.graph.node) == len(model.graph.node) + 2
    x = _on_grid(2 * 3072, 16)
    session = ort.InferenceSession(guarded.SerializeToString(), providers=["CPUExecutionProvider"])
    out, out2 = session.run(["out", "out2"], {"x": x})
    np.testing.assert_array_equal(out.reshape(-1), out2.reshape(-1))


def test_removing_the_guards_gives_back_the_graph_as_it_was():
    model = _gemm_reshape(16, 32, ATTENTION, extra_reshape=[-1, 64, 48, 32])
    guarded, _ = _guarded(model)
    assert sorted(remove_guards(guarded)) == [f"split{GUARD_SUFFIX}", f"split2{GUARD_SUFFIX}"]
    assert guarded.graph == model.graph


def _openvino_outputs(model: onnx.ModelProto, x: np.ndarray) -> np.ndarray:
    from e3dpsm.runtime.openvino_session import compile_config, openvino_core

    core = openvino_core()
    compiled = core.compile_model(core.read_model(model.SerializeToString(), b""), "CPU", compile_config(1))
    return compiled({"x": x})[compiled.outputs[0]]


def test_openvino_fails_to_compile_the_paper_reshape_unless_guarded():
    pytest.importorskip("openvino")
    model = _gemm_reshape(16, 32, ATTENTION)
    with pytest.raises(RuntimeError, match=r"ReshapeTransformation[\s\S]*\[1,48,1,1,1\] is incompatible"):
        _openvino_outputs(model, _on_grid(2 * 3072, 16))
    x = _on_grid(2 * 3072, 16)
    reference = _numpy_reference(model, x, [2, 48, 64, 4, 8])
    np.testing.assert_allclose(_openvino_outputs(_guarded(model)[0], x), reference,
                               rtol=1e-5, atol=1e-5 * np.abs(reference).max())


def test_openvino_scales_the_wrong_axis_unless_guarded():
    """A new second axis that is a multiple of the channels compiles, and OpenVINO scales
    row r of it by channel r % C's scale; with the guard it computes numpy's numbers."""
    pytest.importorskip("openvino")
    model = _gemm_reshape(16, 16, SILENT)
    x = _on_grid(4 * 32, 16)
    reference = _numpy_reference(model, x, [4, 32, 16])
    scale = np.abs(reference).max()
    assert np.abs(_openvino_outputs(model, x) - reference).max() > 0.1 * scale
    np.testing.assert_allclose(_openvino_outputs(_guarded(model)[0], x), reference, rtol=1e-5, atol=1e-5 * scale)


@pytest.mark.slow
def test_paper_full_integer_at_192x256_compiles_and_runs_on_openvino(quant_data, tmp_path: Path):  # noqa: F811
    """`paper` (its fresh weights: zero projection biases, which OpenVINO folds away) quantised
    to full integer at 192 x 256, its budget checked on OpenVINO too: the artifact carries the
    guards, compiles, and steps as ONNX Runtime does; without the guards it does not compile
    when read by `read_model` alone."""
    pytest.importorskip("openvino")
    import e3dpsm
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export import export_step
    from e3dpsm.metrics import joint_errors
    from e3dpsm.quantize import quantize_graph
    from e3dpsm.runtime import StepSession
    from e3dpsm.runtime.openvino_session import OpenVINOStepSession, compile_config, openvino_core
    from e3dpsm.validation.streams import onnx_stream_outputs

    graph = export_step(e3dpsm.create_model("paper").eval(), tmp_path / "step.onnx")
    report = quantize_graph(graph, quant_data, tmp_path / "int8", fast(
        mode="int8", exclude="none", holdout_frames=8, runtimes=("onnxruntime", "openvino")))
    assert set(report["check"]["by_runtime"]) == {"onnxruntime", "openvino"}
    artifact = tmp_path / "int8" / report["artifact"]
    model = onnx.load(str(artifact))
    guards = {n.name for n in model.graph.node if n.name.endswith(GUARD_SUFFIX)}
    assert f"/attention.0/attn/Reshape{GUARD_SUFFIX}" in guards
    lnes = np.asarray(PreparedData.open(quant_data).split("test")[0].lnes[:6], dtype=np.float32)
    on_ort = onnx_stream_outputs(StepSession(artifact, threads=1), lnes, 20.0)["pose"]
    on_openvino = onnx_stream_outputs(OpenVINOStepSession(artifact, threads=1), lnes, 20.0)["pose"]
    # The two runtimes round a QDQ graph their own ways: 0.84 mm at most over 100 frames of
    # this graph, as far as ONNX Runtime's fused kernels from its unfused arithmetic (1.14;
    # benchmarks/results/openvino_int8_paper.md).
    assert joint_errors(on_openvino, on_ort).max() < 1.5
    assert set(remove_guards(model)) == guards
    onnx.save(model, str(tmp_path / "unguarded.onnx"))
    # Read by OpenVINO's read_model alone, as an application may, it does not compile ...
    core = openvino_core()
    with pytest.raises(Exception, match="ReshapeTransformation"):
        core.compile_model(core.read_model(str(tmp_path / "unguarded.onnx")), "CPU", compile_config(1))
    # ... and e3dpsm's read (protect_dequantization) keeps OpenVINO off that path for this
    # graph: it steps as the guarded one does. The five-node graphs above still need the guard.
    unguarded = onnx_stream_outputs(OpenVINOStepSession(tmp_path / "unguarded.onnx", threads=1), lnes, 20.0)["pose"]
    assert joint_errors(unguarded, on_openvino).max() < 1e-3
