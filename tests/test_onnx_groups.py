"""e3dpsm.onnx_groups: which module each node belongs to, the one algorithm behind the
quantiser's candidate groups, the profiler's per-module figures and diagnose."""
from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.onnx_groups import OTHER, SSM, module_scopes, scope_of, tensor_types
from e3dpsm.profiles.flops import group_of
from e3dpsm.profiles.graph_groups import assign_groups

F = TensorProto.FLOAT


def _hand_made() -> onnx.ModelProto:
    """A small graph in the exporter's naming, each node placed to exercise one rule."""
    nodes = [
        helper.make_node("Conv", ["lnes", "w"], ["/stem/Conv_output_0"], name="/stem/Conv"),  # name scope
        # onnxsim renamed it, its output keeps the scope
        helper.make_node("Relu", ["/stem/Conv_output_0"], ["/stages.0/block/Relu_output_0"], name="Relu_3"),
        # a top-level node between two scoped ones: producer and consumer agree
        helper.make_node("Sigmoid", ["/stages.0/block/Relu_output_0"], ["/Sigmoid_output_0"], name="/Sigmoid"),
        helper.make_node("Mul", ["/Sigmoid_output_0", "/stages.0/block/Relu_output_0"], ["/stages.0/Mul_output_0"],
                         name="/stages.0/Mul"),
        # the S5 step, unscoped: anchored by its state tensors, and its activation neighbours
        helper.make_node("Add", ["/stages.0/Mul_output_0", "s5_stage1_re_in"], ["/Add_output_0"], name="/Add"),
        helper.make_node("Mul", ["/Add_output_0", "/Add_output_0"], ["/norm1/Mul_output_0"], name="/norm1/Mul"),
        helper.make_node("Identity", ["/norm1/Mul_output_0"], ["s5_stage1_re_out"], name="/Identity"),
        # shape arithmetic: the Shape reads an activation (its producer's scope), the Slice
        # reads and writes int64 only and belongs to no module
        helper.make_node("Shape", ["/stages.0/Mul_output_0"], ["/Shape_output_0"], name="/Shape"),
        helper.make_node("Slice", ["/Shape_output_0", "starts", "ends"], ["_v_7"], name="Slice_7"),
        helper.make_node("Reshape", ["/norm1/Mul_output_0", "_v_7"], ["/decoder/Reshape_output_0"],
                         name="/decoder/Reshape"),
        # a constant shared by two modules: its consumers disagree
        helper.make_node("Constant", [], ["/Constant_9_output_0"], name="/Constant_9",
                         value=numpy_helper.from_array(np.array(2.0, np.float32))),
        helper.make_node("Mul", ["/decoder/Reshape_output_0", "/Constant_9_output_0"], ["/direct_head/Mul_output_0"],
                         name="Mul_11"),
        helper.make_node("Div", ["/decoder/Reshape_output_0", "/Constant_9_output_0"], ["pose"],
                         name="/delta_head/Div"),
    ]
    graph = helper.make_graph(
        nodes, "hand_made",
        [helper.make_tensor_value_info("lnes", F, [1, 2, 4, 4]),
         helper.make_tensor_value_info("s5_stage1_re_in", F, [1, 3, 2, 2])],
        [helper.make_tensor_value_info("pose", F, None), helper.make_tensor_value_info("s5_stage1_re_out", F, None),
         helper.make_tensor_value_info("/direct_head/Mul_output_0", F, None)],
        [numpy_helper.from_array(np.ones((3, 2, 3, 3), np.float32), "w"),
         numpy_helper.from_array(np.array([0], np.int64), "starts"),
         numpy_helper.from_array(np.array([2], np.int64), "ends")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    return model


HAND_MADE_SCOPES = {
    "/stem/Conv": "stem",
    "Relu_3": "stages.0",
    "/Sigmoid": "stages.0",
    "/stages.0/Mul": "stages.0",
    "/Add": SSM,
    "/norm1/Mul": SSM,
    "/Identity": SSM,
    "/Shape": "stages.0",
    "Slice_7": OTHER,
    "/decoder/Reshape": "decoder",
    "/Constant_9": OTHER,
    "Mul_11": "direct_head",
    "/delta_head/Div": "delta_head",
}


def test_scope_of_reads_the_first_module_component():
    assert scope_of("/stages.0/block1/conv1/Conv") == "stages.0"
    assert scope_of("/attention.3/GridSample_output_0") == "attention.3"
    assert scope_of("/norm1/decoder/Add") == "decoder"  # the first component that is a module
    assert scope_of("/Mul_12") is None and scope_of("Gemm_3") is None and scope_of("/stages.0") is None


def test_hand_made_graph_scopes():
    assert module_scopes(_hand_made()) == HAND_MADE_SCOPES


def test_profiles_groups_are_the_scopes_mapped_to_the_paper_groups():
    model = _hand_made()
    groups = assign_groups(model, tensor_types(model))
    assert groups["Relu_3"] == "cnn" and groups["/Add"] == "ssm" and groups["Mul_11"] == "heads"
    assert groups == {k: group_of(v.split(".")[0]) for k, v in HAND_MADE_SCOPES.items()}


def test_labels_do_not_travel_along_shape_arithmetic():
    """Given as int64, a tensor carries no label: the Reshape's shape input does not make
    the Slice part of the decoder; declared float, it does."""
    model = _hand_made()
    assert module_scopes(model, {"_v_7": TensorProto.INT64, "/Shape_output_0": TensorProto.INT64})["Slice_7"] == OTHER
    assert module_scopes(model, {})["Slice_7"] != OTHER


@pytest.fixture(scope="module")
def tiny_scopes(tiny_step_graph):
    model = onnx.load(str(tiny_step_graph))
    return model, module_scopes(model)


def test_tiny_graph_every_compute_node_in_its_module(tiny_scopes):
    model, scopes = tiny_scopes
    by_op: dict[str, set[str]] = {}
    for node in model.graph.node:
        by_op.setdefault(node.op_type, set()).add(scopes[node.name])
    assert {s.split(".")[0] for s in by_op["Conv"]} <= {"stem", "stages", "attention"}  # attention: its offsets
    assert {s.split(".")[0] for s in by_op["GridSample"]} == {"attention"}
    # every node reading or writing an S5 state is S5 work
    for node in model.graph.node:
        if any(t.startswith("s5_") for t in (*node.input, *node.output)):
            assert scopes[node.name] == SSM, node.name
    # compute ops land in a module; only constants and shape arithmetic may stay outside
    left = {node.op_type for node in model.graph.node if scopes[node.name] == OTHER}
    assert left <= {"Constant", "Shape", "Slice", "Concat", "Gather", "Unsqueeze", "Squeeze", "Cast",
                    "ConstantOfShape", "Reshape", "Range", "Equal", "Where", "Expand"}, left


def test_tiny_graph_quantiser_and_profiler_see_the_same_modules(tiny_scopes):
    from e3dpsm.profiles.flops_onnx import static_shapes
    from e3dpsm.quantize.graph_groups import candidate_groups

    model, scopes = tiny_scopes
    groups = assign_groups(model, static_shapes(model)[1])
    modules = {g.name: set(g.nodes) for g in candidate_groups(model) if g.kind == "module"}
    for name, nodes in modules.items():
        assert {groups[n] for n in nodes} == {group_of(name.split(".")[0])}, name
    # the S5 blocks' own layers (norms, projections) are a candidate of the exclusion search
    assert SSM in modules
