"""Repeating constants stored as a block and a Tile (e3dpsm/onnx_constants.py)."""
from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.onnx_constants import repeating_block, retile_constants


@pytest.mark.parametrize("block_shape, repeats", [((5, 2), (1, 8)), ((3, 4), (6, 1)), ((2, 3), (4, 5)),
                                                  ((7,), (9,)), ((1, 2, 3), (2, 1, 4))])
def test_repeating_block_recovers_the_tiled_block(block_shape: tuple[int, ...], repeats: tuple[int, ...]) -> None:
    block = np.random.default_rng(0).standard_normal(block_shape).astype(np.float32)  # no inner period
    block_found, repeats_found = repeating_block(np.tile(block, repeats))
    np.testing.assert_array_equal(block_found, block)
    assert repeats_found == repeats


def test_repeating_block_leaves_an_array_that_does_not_repeat() -> None:
    array = np.random.default_rng(1).standard_normal((6, 8)).astype(np.float32)
    block, repeats = repeating_block(array)
    assert block.shape == array.shape and repeats == (1, 1)


def test_repeating_block_is_exact_to_the_bit() -> None:
    """One element one float32 step off, or a zero of the other sign, breaks the period."""
    tiled = np.tile(np.array([[0.5, -1.25]], np.float32), (1, 8))
    off = tiled.copy()
    off[0, 9] = np.nextafter(off[0, 9], np.float32(1))
    assert repeating_block(off)[1] == (1, 1)
    signed = np.tile(np.array([[0.0, 2.0]], np.float32), (1, 4))
    signed[0, 6] = -0.0
    assert repeating_block(signed)[1] == (1, 1)
    assert repeating_block(tiled)[1] == (1, 8)


def _graph(origin: np.ndarray, weight: np.ndarray) -> onnx.ModelProto:
    """y = (x + origin) @ weight, z = x * origin: origin read by elementwise ops only."""
    rows, cols = origin.shape
    nodes = [helper.make_node("Add", ["x", "origin"], ["shifted"], name="add"),
             helper.make_node("MatMul", ["shifted", "weight"], ["y"], name="matmul"),
             helper.make_node("Mul", ["x", "origin"], ["z"], name="mul")]
    graph = helper.make_graph(
        nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [rows, cols])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [rows, weight.shape[1]]),
         helper.make_tensor_value_info("z", TensorProto.FLOAT, [rows, cols])],
        [numpy_helper.from_array(origin, "origin"), numpy_helper.from_array(weight, "weight")])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)


def _run(model: onnx.ModelProto, x: np.ndarray) -> list[np.ndarray]:
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(None, {"x": x})


def test_retile_constants_keeps_the_function_and_leaves_weights_alone() -> None:
    rng = np.random.default_rng(2)
    origin = np.tile(rng.standard_normal((64, 2)).astype(np.float32), (1, 16))  # 64 x 32, 8 KB
    weight = np.tile(rng.standard_normal((32, 1)).astype(np.float32), (1, 64))  # repeats, but a MatMul weight
    model = _graph(origin, weight)
    x = rng.standard_normal(origin.shape).astype(np.float32)
    before = _run(model, x)
    size = model.ByteSize()
    retiled = retile_constants(model)
    onnx.checker.check_model(model, full_check=True)
    assert retiled.constants == 1
    assert retiled.bytes_saved == size - model.ByteSize()
    # the repeats gone, less the names and the node that replace them
    assert origin.nbytes - 64 * 2 * 4 - 200 < retiled.bytes_saved < origin.nbytes - 64 * 2 * 4
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    assert "origin" not in inits and inits["origin::block"].shape == (64, 2)
    np.testing.assert_array_equal(inits["origin::repeats"], [1, 16])
    np.testing.assert_array_equal(inits["weight"], weight)
    tile = model.graph.node[0]
    assert tile.op_type == "Tile" and list(tile.output) == ["origin"]
    for got, want in zip(_run(model, x), before):
        np.testing.assert_array_equal(got, want)  # the same tensor, bit for bit


def test_retile_constants_skips_small_gains_and_graph_outputs() -> None:
    small = np.tile(np.float32([[1.0, 2.0]]), (4, 8))  # 256 bytes: not worth a node
    model = _graph(small, np.eye(16, dtype=np.float32))
    assert retile_constants(model).constants == 0
    big = np.tile(np.float32([[1.0, 2.0]]), (64, 16))
    model = _graph(big, np.eye(32, dtype=np.float32))
    model.graph.output.append(helper.make_tensor_value_info("origin", TensorProto.FLOAT, list(big.shape)))
    assert retile_constants(model).constants == 0


def test_retile_constants_leaves_float16_constants_alone() -> None:
    """ONNX Runtime 1.31's CPU Tile has no float16 kernel: such a Tile would be neither folded
    on load nor run without casts, so float16 constants stay as they are."""
    origin = np.tile(np.float32([[1.0, 2.0]]), (64, 16))
    model = _graph(origin, np.eye(32, dtype=np.float32))
    model.graph.initializer[0].CopyFrom(numpy_helper.from_array(origin.astype(np.float16), "origin"))
    assert retile_constants(model).constants == 0
