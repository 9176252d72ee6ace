"""The quantised artifact's compaction (quantize/compact.py): short names for what the
quantiser added, one copy of equal constants, no stored shapes; the same poses, every name
of the float graph kept, diagnose's plan unchanged."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.quantize.compact import compact_qdq, graph_names


# -- a hand-made QDQ graph -----------------------------------------------------------------

def _qdq_conv_graph() -> onnx.ModelProto:
    """x -> Q -> DQ -> Conv(DQ(w)) -> Q -> DQ -> y, with two equal all-zero weight zero points
    (two convs), a tensor already named `q0` and a protected float initializer."""
    rng = np.random.default_rng(0)
    inits = [
        numpy_helper.from_array(np.array(0.02, np.float32), "x_scale_long_name"),
        numpy_helper.from_array(np.array(128, np.uint8), "x_zero_point_long_name"),
        numpy_helper.from_array(rng.integers(-127, 128, (4, 3, 3, 3)).astype(np.int8), "w1_quantized"),
        numpy_helper.from_array(np.full(4, 0.01, np.float32), "w1_scale"),
        numpy_helper.from_array(np.zeros(4, np.int8), "w1_zero_point"),
        numpy_helper.from_array(rng.integers(-127, 128, (4, 4, 1, 1)).astype(np.int8), "w2_quantized"),
        numpy_helper.from_array(np.full(4, 0.01, np.float32), "w2_scale"),  # equal to w1_scale
        numpy_helper.from_array(np.zeros(4, np.int8), "w2_zero_point"),     # equal to w1_zero_point
        numpy_helper.from_array(np.full(4, 0.01, np.float32), "float_gain"),  # equal, but the float graph's
        numpy_helper.from_array(np.array(0.05, np.float32), "y_scale"),
        numpy_helper.from_array(np.array(128, np.uint8), "y_zero_point"),
    ]
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "x_scale_long_name", "x_zero_point_long_name"], ["x_QuantizeLinear_Output"], name="x_QuantizeLinear"),
        helper.make_node("DequantizeLinear", ["x_QuantizeLinear_Output", "x_scale_long_name", "x_zero_point_long_name"], ["x_DequantizeLinear_Output"], name="x_DequantizeLinear"),
        helper.make_node("DequantizeLinear", ["w1_quantized", "w1_scale", "w1_zero_point"], ["w1_DequantizeLinear_Output"], name="w1_DequantizeLinear", axis=0),
        helper.make_node("Conv", ["x_DequantizeLinear_Output", "w1_DequantizeLinear_Output"], ["q0"], name="conv1", pads=[1, 1, 1, 1]),
        helper.make_node("DequantizeLinear", ["w2_quantized", "w2_scale", "w2_zero_point"], ["w2_DequantizeLinear_Output"], name="w2_DequantizeLinear", axis=0),
        helper.make_node("Conv", ["q0", "w2_DequantizeLinear_Output"], ["conv2_out"], name="conv2"),
        helper.make_node("Mul", ["conv2_out", "float_gain_4d"], ["scaled"], name="mul"),
        helper.make_node("QuantizeLinear", ["scaled", "y_scale", "y_zero_point"], ["scaled_QuantizeLinear_Output"], name="scaled_QuantizeLinear"),
        helper.make_node("DequantizeLinear", ["scaled_QuantizeLinear_Output", "y_scale", "y_zero_point"], ["y"], name="scaled_DequantizeLinear"),
    ]
    inits.append(numpy_helper.from_array(np.full((1, 4, 1, 1), 0.5, np.float32), "float_gain_4d"))
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 5, 5])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 5, 5])], inits,
                              value_info=[helper.make_tensor_value_info("q0", TensorProto.FLOAT, [1, 4, 5, 5])])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def _run(model: onnx.ModelProto, x: np.ndarray) -> np.ndarray:
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(None, {"x": x})[0]


def test_compaction_renames_only_what_the_quantiser_added_and_keeps_the_outputs() -> None:
    model = _qdq_conv_graph()
    before = onnx.ModelProto()
    before.CopyFrom(model)
    keep = {"x", "y", "q0", "conv1", "conv2", "mul", "conv2_out", "scaled", "float_gain", "float_gain_4d"}
    result = compact_qdq(model, keep)
    onnx.checker.check_model(model, full_check=True)

    names = graph_names(model)
    assert keep <= names  # the float graph's names, the graph's inputs and outputs
    assert not model.graph.value_info and result.value_info_dropped == 1
    # The Q/DQ nodes and their tensors, numbered in graph order; `q0` was a kept name.
    by_op = {n.name: n for n in model.graph.node}
    assert [n.name for n in model.graph.node if n.op_type == "QuantizeLinear"] == ["q0_", "q1"]
    assert by_op["q0_"].output[0] == "q0_" and by_op["q0_"].input[1:] == ["q0.s", "q0.z"]
    assert by_op["dq0"].input == ["q0_", "q0.s", "q0.z"]  # the pair shares its scale and zero point
    assert by_op["dq1"].input[0] == "dq1.w" and by_op["dq1"].input[2] == "dq1.z"
    assert by_op["dq3"].output[0] == "y"  # a graph output keeps its name
    assert not any("Linear" in name or "_quantized" in name or "_zero_point" in name for name in names)
    # Equal constants: one copy. The float graph's initializer keeps its name and the
    # quantiser's equal scales read it; the second all-zero zero point reads the first.
    assert by_op["dq1"].input[1] == by_op["dq2"].input[1] == "float_gain"
    assert by_op["dq2"].input[2] == "dq1.z"
    assert by_op["q1"].input[2] == by_op["dq3"].input[2] == "q0.z"  # both activation zero points are 128
    assert result.initializers_shared == 4
    assert len(model.graph.initializer) == len(before.graph.initializer) - 4
    assert result.bytes_saved == before.ByteSize() - model.ByteSize() > 0
    x = np.random.default_rng(1).standard_normal((1, 3, 5, 5)).astype(np.float32)
    np.testing.assert_array_equal(_run(model, x), _run(before, x))


def test_compaction_without_a_keep_list_still_keeps_the_graph_inputs_and_outputs() -> None:
    model = _qdq_conv_graph()
    before = onnx.ModelProto()
    before.CopyFrom(model)
    compact_qdq(model)
    onnx.checker.check_model(model, full_check=True)
    assert [o.name for o in model.graph.output] == ["y"] and [i.name for i in model.graph.input] == ["x"]
    assert next(n for n in model.graph.node if "y" in n.output).op_type == "DequantizeLinear"
    x = np.random.default_rng(2).standard_normal((1, 3, 5, 5)).astype(np.float32)
    np.testing.assert_array_equal(_run(model, x), _run(before, x))


def test_compaction_leaves_graphs_with_subgraphs_named_as_they_are() -> None:
    model = _qdq_conv_graph()
    branch = helper.make_graph([helper.make_node("Identity", ["y"], ["z"])], "b", [],
                               [helper.make_tensor_value_info("z", TensorProto.FLOAT, None)])
    model.graph.node.append(helper.make_node("If", ["cond"], ["w"], name="if", then_branch=branch, else_branch=branch))
    names = graph_names(model)
    result = compact_qdq(model)
    assert result.renamed == 0 and result.initializers_shared == 0 and graph_names(model) == names


# -- the trained tiny, full int8 and with 16-bit nodes ---------------------------------------

@pytest.fixture(scope="module")
def quantised_tiny(tmp_path_factory, trained_graph: Path, quant_data: Path, calibrated_tiny: dict) -> dict:
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize.static import StaticConfig, quantize_int8

    work = tmp_path_factory.mktemp("compact")
    pre, cache = calibrated_tiny["pre"], calibrated_tiny["cache"]
    convs = [n.name for n in onnx.load(str(pre)).graph.node if n.op_type == "Conv"][:6]
    graphs = {}
    for label, int16 in (("full_int8", []), ("int16", convs)):
        out = work / f"{label}.onnx"
        quantize_int8(pre, out, StaticConfig(), exclude=[], cache=cache, int16_nodes=int16)
        graphs[label] = out
    lnes = np.asarray(PreparedData.open(quant_data).split("val")[0].lnes[:24], dtype=np.float32)
    return {"graphs": graphs, "lnes": lnes, "source": onnx.load(str(trained_graph)), "reference": trained_graph}


def _stream(path_or_model, lnes: np.ndarray, folder: Path) -> dict[str, np.ndarray]:
    from e3dpsm.runtime import StepSession
    from e3dpsm.validation.streams import onnx_stream_outputs

    if isinstance(path_or_model, onnx.ModelProto):
        path = folder / "compacted.onnx"
        onnx.save(path_or_model, str(path))
        path_or_model = path
    return onnx_stream_outputs(StepSession(path_or_model, threads=1), lnes, 20.0)


# Renaming can change the order ONNX Runtime's optimisers visit float nodes in (seen on the
# committed `small` with 16-bit nodes: 1.2e-4 mm at most, float32 round-off of mm poses);
# the quantised arithmetic itself is unchanged. 1e-3 mm is a thousandth of the 1% INT8 budget
# of a model with 100 mm MPJPE.
ROUND_OFF_MM = 1e-3


@pytest.mark.parametrize("label", ["full_int8", "int16"])
def test_compacted_graph_gives_the_same_poses_and_keeps_every_float_graph_name(quantised_tiny, label: str,
                                                                                tmp_path: Path) -> None:
    path = quantised_tiny["graphs"][label]
    model = onnx.load(str(path))
    float_names = graph_names(quantised_tiny["source"]) & graph_names(model)
    result = compact_qdq(model, graph_names(quantised_tiny["source"]))
    onnx.checker.check_model(model)
    assert float_names <= graph_names(model) and result.renamed > 100
    assert not model.graph.value_info
    # Smaller by at least a tenth here (the tiny's weights are few, its names as long as small's).
    assert model.ByteSize() < 0.9 * onnx.load(str(path)).ByteSize()
    before = _stream(path, quantised_tiny["lnes"], tmp_path)
    after = _stream(model, quantised_tiny["lnes"], tmp_path)
    for name, values in before.items():
        assert np.abs(after[name] - values).max() <= ROUND_OFF_MM, name
    # The tolerance bites: the quantisation itself moves the poses by far more.
    fp32 = _stream(quantised_tiny["reference"], quantised_tiny["lnes"], tmp_path)
    assert np.abs(fp32["pose"] - before["pose"]).max() > 100 * ROUND_OFF_MM


def test_diagnose_plans_the_compacted_graph_as_the_uncompacted_one(quantised_tiny) -> None:
    from e3dpsm.golden.diagnose import make_plan
    from e3dpsm.graph_metadata import GraphMetadata

    reference = quantised_tiny["source"]
    model = onnx.load(str(quantised_tiny["graphs"]["full_int8"]))
    meta = GraphMetadata.from_onnx(reference)
    plain = make_plan(reference, model, meta)
    compact_qdq(model, graph_names(reference))
    compacted = make_plan(reference, model, meta)
    assert compacted.boundary == plain.boundary and compacted.states == plain.states
    assert compacted.model_name.keys() == plain.model_name.keys() and len(plain.qdq) > 20
    assert {t: g for t, (_, g) in compacted.qdq.items()} == {t: g for t, (_, g) in plain.qdq.items()}
    assert any(plain.model_name[t] != compacted.model_name[t] for t in plain.model_name)  # it did rename


def test_quantize_writes_the_compacted_artifact_and_reports_it(int8_dir: Path, trained_graph: Path) -> None:
    report = json.loads((int8_dir / "report.json").read_text())
    model = onnx.load(str(int8_dir / report["artifact"]))
    written = report["written"]
    compaction = written["saved"]["compaction"]
    assert compaction["renamed"] > 100 and compaction["bytes_saved"] > 0
    assert written["bytes"] == (int8_dir / report["artifact"]).stat().st_size
    ratio = written["bytes"] / written["source_bytes"]
    saved = compaction["bytes_saved"] + written["saved"]["retiled_constants"]["bytes_saved"]  # onnx_constants.py too
    assert f"MB ({ratio:.3f}x), {saved / 1e3:.0f} kB less" in (int8_dir / "report.md").read_text()
    assert not model.graph.value_info
    assert not any(n.name.endswith(("QuantizeLinear", "DequantizeLinear")) for n in model.graph.node)
    assert {n.name for n in onnx.load(str(trained_graph)).graph.node} & {n.name for n in model.graph.node}
    assert json.loads(next(p.value for p in model.metadata_props if p.key == "e3dpsm.quantization"))[
        "budget"] == report["quantization"]["budget"]
