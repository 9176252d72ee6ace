"""What every non-ONNX step artifact's runner shares (ExecuTorch, LiteRT, Core ML, TensorRT):
the `GraphStepper` surface of `StepSession`, so the stream runtime, golden check, validate,
serve and profile drive any of them alike. A subclass loads its runtime and implements
`_run_one(feeds) -> {name: array}` for one batch row; the artifacts are built for one
stream (batch 1), so a batch of several streams (`e3dpsm run` over several files) is
stepped row by row here. Torch-free."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from e3dpsm.errors import InputError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.runtime.session import MetadataStepper
from e3dpsm.runtime.stepping import StateArrays


class ArtifactSession(MetadataStepper):
    """`step(lnes, state, window_ms) -> (outputs, state)` over a converted artifact.

    Subclasses set `runtime` (a name for reports) and call `_bind(path, meta, inputs,
    outputs)` with the names the artifact itself exposes, checked here against the
    metadata's contract."""

    runtime = "artifact"

    def _bind(self, path: str | os.PathLike, meta: GraphMetadata, inputs: list[str], outputs: list[str]) -> None:
        self.path = Path(path)
        self.meta = meta
        self._inputs, self._outputs = list(inputs), list(outputs)
        expected_in = {meta.frame_input["name"], meta.window_input["name"], *(s.input_name for s in meta.states)}
        expected_out = {*meta.output_names, *(s.output_name for s in meta.states)}
        if set(inputs) != expected_in or not expected_out <= set(outputs):
            raise InputError(f"{path}: inputs {sorted(inputs)} / outputs {sorted(outputs)} do not match its "
                             f"metadata ({sorted(expected_in)} / {sorted(expected_out)}); convert it again")

    def run_feeds(self, feeds: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], StateArrays]:
        batch = int(feeds[self.meta.frame_input["name"]].shape[0])
        rows = [self._run_one({name: value[i: i + 1] for name, value in feeds.items()}) for i in range(batch)]
        named = {name: np.concatenate([row[name] for row in rows]) if batch > 1 else rows[0][name]
                 for name in rows[0]}
        outputs = {name: named[name] for name in self.meta.output_names}
        return outputs, {s.name: named[s.output_name] for s in self.meta.states}

    def _run_one(self, feeds: Mapping[str, np.ndarray]) -> dict[str, Any]:
        raise NotImplementedError
