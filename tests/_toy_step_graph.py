"""A step graph small enough to write out in numpy, with the metadata the export writes: one
state `mem_a` [3] with a non-zero initial value, a dynamic batch, per-stream windows."""
from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.state import StateSpec, state_input_name, state_output_name

STATE = "mem_a"
INIT = (0.5, -1.0, 2.0)  # a non-zero initial state: a session that starts from zeros shows


def toy_step_graph(states: tuple[StateSpec, ...] | None = None) -> onnx.ModelProto:
    """s' = s + window_ms / 1000 + sum(lnes) per stream; pose = 2 s'; `extra` = s' - s, an output
    the metadata does not list."""
    inits = [numpy_helper.from_array(np.array([1, 2, 3], np.int64), "axes"),
             numpy_helper.from_array(np.array([-1, 1], np.int64), "column"),
             numpy_helper.from_array(np.array(1e-3, np.float32), "milli"),
             numpy_helper.from_array(np.array(2.0, np.float32), "two")]
    nodes = [helper.make_node("ReduceSum", ["lnes", "axes"], ["total"], keepdims=0),
             helper.make_node("Mul", ["window_ms", "milli"], ["seconds"]),
             helper.make_node("Add", ["total", "seconds"], ["drive"]),
             helper.make_node("Reshape", ["drive", "column"], ["drive_col"]),
             helper.make_node("Add", [state_input_name(STATE), "drive_col"], [state_output_name(STATE)]),
             helper.make_node("Mul", [state_output_name(STATE), "two"], ["pose"]),
             helper.make_node("Sub", [state_output_name(STATE), state_input_name(STATE)], ["extra"])]
    value = lambda name, *shape: helper.make_tensor_value_info(name, TensorProto.FLOAT, ["B", *shape])  # noqa: E731
    graph = helper.make_graph(nodes, "toy", [value("lnes", 2, 2, 3), value("window_ms"), value(state_input_name(STATE), 3)],
                              [value("pose", 3), value(state_output_name(STATE), 3), value("extra", 3)], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    GraphMetadata(states=states or (StateSpec(STATE, (3,), init=INIT),),
                  inputs={"frame": {"name": "lnes", "shape": ["B", 2, 2, 3]}, "window": {"name": "window_ms", "shape": ["B"]}},
                  outputs=[{"name": "pose"}], config={"variant": "toy"}, joints=["a", "b", "c"]).write_to(model)
    return model



def toy_lnes(batch: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, (batch, 2, 2, 3)).astype(np.float32)


def toy_numpy_step(lnes: np.ndarray, state: np.ndarray, window_ms) -> np.ndarray:
    """The graph's state update in float64."""
    return state + (lnes.astype(np.float64).sum(axis=(1, 2, 3)) + np.asarray(window_ms) / 1000.0)[:, None]
