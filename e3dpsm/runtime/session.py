"""Drive an exported step graph with onnxruntime and numpy alone.

The state layout, input names and window-length convention are read from the graph's
metadata (e3dpsm.graph_metadata), never re-derived from Python model code.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from e3dpsm.errors import DataError, InputError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.runtime.stepping import StateArrays, Stepper
from e3dpsm.state import check_state_shapes, initial_states


def exact_arithmetic_options() -> Any:
    """ONNX Runtime session options that run a graph as its operators define it: graph
    optimisations off, so a QuantizeLinear / DequantizeLinear pair is computed in float
    instead of being fused into an integer kernel. An INT8 graph then gives the same numbers
    on any host; with fusion, ONNX Runtime's x86 U8S8 kernels without VNNI add pairs of
    u8 x s8 products in saturating 16-bit sums (utils/isa.py, tests/test_isa.py)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    return options


def make_session(
    path: str | os.PathLike, *, threads: int | None = None, providers: Sequence[str] | None = None,
    options: Any = None, spin: bool = True,
):
    """An onnxruntime.InferenceSession with a bounded thread count (edge devices share cores).

    `spin=False` stops idle worker threads from busy-waiting, which matters when the same
    cores also run something else between steps (PyTorch in a parity run, windowing).
    """
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise DataError(f"model {path} does not exist")
    so = options or ort.SessionOptions()
    # ONNX Runtime fuses a DequantizeLinear'd 8-bit weight feeding a float MatMul/Gemm into
    # MatMulNBits, which by default (accuracy level 4) quantises the activations to int8 on
    # the fly: computations the graph does not define, rounded differently by x86 and ARM
    # kernels (0.99 mm apart on the committed `small`'s weight-only nodes, and 2.1 mm from
    # level 1 on x86 alone: docs/edge.md, "ARM without ARM hardware"). Level 1 computes in
    # float32, as the graph says.
    so.add_session_config_entry("session.qdq_matmulnbits_accuracy_level", "1")
    if threads:
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
    if not spin:
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        return ort.InferenceSession(str(path), sess_options=so, providers=list(providers or ["CPUExecutionProvider"]))
    except Exception as exc:  # ORT raises its own exception types for corrupt / invalid files
        raise DataError(f"onnxruntime cannot load {path}: {str(exc).splitlines()[0][:300]}") from exc


def build_feeds(
    meta: GraphMetadata, lnes: np.ndarray, state: Mapping[str, np.ndarray], window_ms: float | np.ndarray
) -> dict[str, np.ndarray]:
    """The input dict of one step for any runtime, checked against the graph's metadata."""
    frame_shape = tuple(meta.frame_input["shape"][1:])
    if not isinstance(lnes, np.ndarray) or lnes.ndim != 4 or tuple(lnes.shape[1:]) != frame_shape:
        got = list(lnes.shape) if isinstance(lnes, np.ndarray) else type(lnes).__name__
        raise InputError(f"LNES has shape {got}, expected [B, {', '.join(map(str, frame_shape))}]")
    if lnes.dtype != np.float32:
        raise InputError(f"LNES has dtype {lnes.dtype}, expected float32")
    batch = lnes.shape[0]
    check_state_shapes(meta.states, {k: v.shape for k, v in state.items()}, batch)
    window = np.asarray(window_ms, dtype=np.float32).reshape(-1)
    if window.shape[0] == 1 and batch > 1:
        window = np.repeat(window, batch)
    if window.shape[0] != batch or not np.all(window > 0):
        raise InputError(f"window_ms must hold one positive value or {batch}, got {window.tolist()}")
    feeds = {meta.frame_input["name"]: lnes, meta.window_input["name"]: window}
    for spec in meta.states:
        feeds[spec.input_name] = np.ascontiguousarray(state[spec.name], dtype=np.float32)
    return feeds


class MetadataStepper:
    """What every runtime's step session derives from its metadata alone: the states, their
    initial values, the checked feeds of a step, and `step` = `run_feeds(feeds(...))`. A
    session sets `meta` and implements `run_feeds`; `_inputs` / `_outputs` name what its
    runtime exposes."""

    meta: GraphMetadata
    _inputs: list[str]
    _outputs: list[str]

    @property
    def states(self):
        return self.meta.states

    def input_names(self) -> list[str]:
        return list(self._inputs)

    def output_names_all(self) -> list[str]:
        return list(self._outputs)

    def init_state(self, batch: int = 1) -> StateArrays:
        return initial_states(self.meta.states, batch)

    def feeds(self, lnes: np.ndarray, state: Mapping[str, np.ndarray], window_ms: float | np.ndarray) -> dict[str, np.ndarray]:
        """The input dict of one step, checked against the metadata."""
        return build_feeds(self.meta, lnes, state, window_ms)

    def run_feeds(self, feeds: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], StateArrays]:
        raise NotImplementedError

    def step(self, lnes: np.ndarray, state: Mapping[str, np.ndarray],
             window_ms: float | np.ndarray) -> tuple[dict[str, np.ndarray], StateArrays]:
        return self.run_feeds(self.feeds(lnes, state, window_ms))


class StepSession(MetadataStepper):
    """One exported E-3DPSM step graph: `step(lnes, state, window_ms) -> (outputs, state)`
    (a `GraphStepper`).

    `all_outputs=True`: `step`'s outputs hold every graph output by name, not only the
    metadata's pose outputs; diagnose exposes intermediate tensors as extra graph outputs
    and reads them there.
    """

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None,
                 providers: Sequence[str] | None = None, options: Any = None, spin: bool = True,
                 all_outputs: bool = False) -> None:
        self.path = Path(path)
        self.all_outputs = all_outputs
        self.session = make_session(path, threads=threads, providers=providers, options=options, spin=spin)
        self.meta = GraphMetadata.from_session(self.session, source=str(path))
        self.frame_name = self.meta.frame_input["name"]
        self.window_name = self.meta.window_input["name"]
        self.output_names = [o.name for o in self.session.get_outputs()]
        graph_inputs = {i.name for i in self.session.get_inputs()}
        expected = {self.frame_name, self.window_name, *(s.input_name for s in self.meta.states)}
        if graph_inputs != expected:
            raise InputError(
                f"{path}: graph inputs {sorted(graph_inputs)} do not match its metadata {sorted(expected)}"
            )

    def input_names(self) -> list[str]:
        return [i.name for i in self.session.get_inputs()]

    def output_names_all(self) -> list[str]:
        return list(self.output_names)

    def run_feeds(self, feeds: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], StateArrays]:
        return self.collect(self.run_raw(feeds))

    def run_raw(self, feeds: Mapping[str, np.ndarray]) -> list[np.ndarray]:
        """The runtime's own call alone: every graph output, in `output_names` order (the
        profile times it apart from the Python around it)."""
        return self.session.run(self.output_names, dict(feeds))

    def collect(self, values: Sequence[np.ndarray]) -> tuple[dict[str, np.ndarray], StateArrays]:
        """`run_raw`'s values as (outputs, next state)."""
        named = dict(zip(self.output_names, values))
        outputs = named if self.all_outputs else {name: named[name] for name in self.meta.output_names}
        new_state = {s.name: named[s.output_name] for s in self.meta.states}
        return outputs, new_state


class CarriedStateRunner:
    """Any `Stepper` stepping one stream at one window length with its own carried state:
    `reset()` / `step(lnes)`, the runner protocol of the profiler and the latency timers."""

    def __init__(self, session: Stepper, window_ms: float) -> None:
        self.session = session
        self.window_ms = window_ms
        self.reset()

    def reset(self) -> None:
        self.state = self.session.init_state(1)

    def step(self, lnes: np.ndarray) -> None:
        _, self.state = self.session.step(lnes, self.state, self.window_ms)
