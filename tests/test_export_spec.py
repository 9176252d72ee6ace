"""The step graph's declarative I/O spec and metadata (export/spec.py) for the tiny variant,
against shapes written out here from its config (192 x 256 LNES of 2 polarities, 16 joints,
the tiny's seven states) and DESIGN.md's metadata contract; `declare_on` on a hand-made graph."""
from __future__ import annotations

import dataclasses

import onnx
import pytest
from onnx import TensorProto, helper

import e3dpsm
from e3dpsm.export.spec import (FRAME_INPUT, WINDOW_INPUT, StepIOSpec, TensorSpec, graph_metadata, step_io_spec)
from e3dpsm.joints import JOINT_NAMES, PARENTS

# The tiny's states, as its S5 stages (1 and 4) and Kalman fusion lay them out.
TINY_STATES = (("s5_stage1_re", (48, 64, 4)), ("s5_stage1_im", (48, 64, 4)), ("s5_stage4_re", (6, 8, 12)),
               ("s5_stage4_im", (6, 8, 12)), ("fusion_pose", (16, 3)), ("fusion_cov", (16, 3)),
               ("fusion_initialised", (1,)))


@pytest.fixture(scope="module")
def tiny() -> e3dpsm.E3DPSM:
    return e3dpsm.create_model("tiny").eval()


@pytest.mark.parametrize("batch", ["batch", 3])
def test_the_spec_lists_every_tensor_in_order_with_its_shape(tiny, batch) -> None:
    spec = step_io_spec(tiny, batch)
    assert [(t.name, t.shape, t.dtype) for t in spec.inputs] == [
        ("lnes", (batch, 2, 192, 256), "float32"), ("window_ms", (batch,), "float32"),
        *((f"{name}_in", (batch, *shape), "float32") for name, shape in TINY_STATES)]
    assert [(t.name, t.shape, t.dtype) for t in spec.outputs] == [
        ("pose", (batch, 16, 3), "float32"), ("pose_direct", (batch, 16, 3), "float32"),
        ("pose_delta", (batch, 16, 3), "float32"),
        *((f"{name}_out", (batch, *shape), "float32") for name, shape in TINY_STATES)]
    assert spec.input_names == [t.name for t in spec.inputs] and spec.output_names == [t.name for t in spec.outputs]
    assert (FRAME_INPUT, WINDOW_INPUT) == ("lnes", "window_ms")


def test_dynamic_axes_name_the_batch_axis_of_every_tensor_and_only_where_it_is_dynamic(tiny) -> None:
    dynamic = step_io_spec(tiny)
    names = [*dynamic.input_names, *dynamic.output_names]
    assert dynamic.dynamic_axes == {name: {0: "batch"} for name in names}
    assert step_io_spec(tiny, 1).dynamic_axes == {}
    assert TensorSpec("x", ("n", 3, "m")).dynamic_axes == {0: "n", 2: "m"}
    assert TensorSpec("x", (1, 3)).dtype == "float32"


def test_specs_are_immutable(tiny) -> None:
    """A spec is a value the exporter, the metadata and the runtimes share: none can change it."""
    spec = step_io_spec(tiny)
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.inputs = ()
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.inputs[0].shape = (1,)


def test_declare_on_writes_the_shapes_and_axis_names_and_leaves_the_rest() -> None:
    graph = helper.make_graph(
        [helper.make_node("Identity", ["a"], ["b"]), helper.make_node("Identity", ["c"], ["d"])], "g",
        [helper.make_tensor_value_info("a", TensorProto.FLOAT, [7]),
         helper.make_tensor_value_info("c", TensorProto.INT64, ["old", 5])],
        [helper.make_tensor_value_info("b", TensorProto.FLOAT, [7]),
         helper.make_tensor_value_info("d", TensorProto.INT64, ["old", 5])])
    model = helper.make_model(graph)
    spec = StepIOSpec(inputs=(TensorSpec("a", ("batch", 2, 4)),), outputs=(TensorSpec("b", (1, "t")),))
    spec.declare_on(model)

    def dims(value: onnx.ValueInfoProto) -> list:
        return [d.dim_param or d.dim_value for d in value.type.tensor_type.shape.dim]

    assert [dims(v) for v in model.graph.input] == [["batch", 2, 4], ["old", 5]]
    assert [dims(v) for v in model.graph.output] == [[1, "t"], ["old", 5]]
    a = model.graph.input[0].type.tensor_type.shape.dim
    assert (a[0].dim_param, a[0].HasField("dim_value"), a[1].dim_value, a[1].HasField("dim_param")) == (
        "batch", False, 2, False)
    assert [v.type.tensor_type.elem_type for v in model.graph.input] == [TensorProto.FLOAT, TensorProto.INT64]


@pytest.mark.parametrize("batch", ["batch", 2])
def test_graph_metadata_is_the_design_contract(tiny, batch) -> None:
    meta = graph_metadata(tiny, {"source": "test"}, batch=batch)
    cfg = tiny.config
    assert meta.inputs["frame"] == {
        "name": "lnes", "shape": [batch, 2, 192, 256], "dtype": "float32",
        "encoding": "LNES: (t - t0) / T of the latest event per pixel in [t0, t0 + T), "
                    "channel = polarity (0 negative, 1 positive), 0 where no event",
        "sensor_hw": [480, 640]}
    assert meta.inputs["window"] == {
        "name": "window_ms", "shape": [batch], "dtype": "float32", "unit": "ms", "train_window_ms": 20.0,
        "doc": "length T of the window each frame covers; one graph serves 20, 25 and 50 ms"}
    assert meta.outputs == [
        {"name": "pose", "shape": [batch, 16, 3], "dtype": "float32", "unit": "mm",
         "doc": "fused 3D pose (the model's output), millimetres, fisheye camera frame"},
        {"name": "pose_direct", "shape": [batch, 16, 3], "dtype": "float32", "unit": "mm",
         "doc": "direct-regression 3D pose, millimetres"},
        {"name": "pose_delta", "shape": [batch, 16, 3], "dtype": "float32", "unit": "mm",
         "doc": "predicted pose change since the previous step, millimetres"}]
    static = {} if batch == "batch" else {"static_batch": batch}
    assert meta.config == {"variant": "tiny", "train_window_ms": 20.0, "fusion": "learned",
                           "model_config": cfg.to_dict(), **static, "source": "test"}
    # states keep the layout contract's dynamic batch axis even in a static graph
    assert [(s.name, tuple(s.shape)) for s in meta.states] == list(TINY_STATES)
    assert meta.joints == list(JOINT_NAMES) and len(meta.joints) == 16
    assert meta.extra == {"e3dpsm.parents": str(list(PARENTS))}
    assert graph_metadata(tiny).config == {"variant": "tiny", "train_window_ms": 20.0, "fusion": "learned",
                                           "model_config": cfg.to_dict()}
