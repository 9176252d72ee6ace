"""The one stepping protocol: `init_state(batch)` and `step(lnes, state, window_ms) ->
(outputs, state)`, numpy in and numpy out, the caller carrying the states.

Every consumer that steps a model frame by frame (parity, golden record and check,
diagnose, the latency timers) is written against this protocol, so an ONNX Runtime
session, an OpenVINO session and the PyTorch model (`e3dpsm.export.torch_stepper`, kept
beside the exporter because it needs torch) are interchangeable there. Torch-free.
"""
from __future__ import annotations

from typing import Mapping, Protocol

import numpy as np

from e3dpsm.graph_metadata import GraphMetadata

StateArrays = dict[str, np.ndarray]


class Stepper(Protocol):
    """A model stepped one frame at a time: `lnes` is float32 [B, 2, H, W], `state` the dict
    `init_state` returned (or the previous step did), keyed by state name."""

    def init_state(self, batch: int = 1) -> StateArrays: ...

    def step(self, lnes: np.ndarray, state: Mapping[str, np.ndarray],
             window_ms: float) -> tuple[dict[str, np.ndarray], StateArrays]: ...


class GraphStepper(Stepper, Protocol):
    """A stepper over an exported graph: what checks against the graph's own contract (its
    metadata and input / output names) need on top of stepping."""

    meta: GraphMetadata

    def input_names(self) -> list[str]: ...

    def output_names_all(self) -> list[str]: ...

