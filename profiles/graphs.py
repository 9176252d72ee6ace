"""The graphs a profile runs: the fp32 step graph (exported here from the PyTorch model, or
given), its `--static-batch` export when a static target is selected (exported here too, and
held to the PyTorch model's parity before anything is timed on it), and the quantised graphs
given."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from e3dpsm.errors import ConfigError, DataError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.profiles.flops_onnx import load_graph
from e3dpsm.profiles.targets import STATIC_FP32, Target

GRAPH_NAME = "step_fp32.onnx"
STATIC_GRAPH_NAME = "step_fp32_static.onnx"
# Carried steps of the static export's parity check: the second step already runs the
# Kalman fusion's update branch; more only lengthen the profile.
STATIC_PARITY_STEPS = 8


def graph_metadata(path: Path) -> GraphMetadata:
    return GraphMetadata.from_onnx(load_graph(path), source=str(path))


def given_graphs(model: str | None, int8: str | None, fp16: str | None, static: str | None) -> dict[str, Path | None]:
    """The graphs named on the command line, checked (exist, carry e3dpsm metadata, a
    static graph has a fixed batch) before anything is exported or measured."""
    graphs = {"fp32": _existing(model, "--model"), "int8": _existing(int8, "--int8-model"),
              "fp16": _existing(fp16, "--fp16-model"), STATIC_FP32: _existing(static, "--static-model")}
    for path in graphs.values():
        if path is not None:
            graph_metadata(path)  # MetadataError (exit 2) if it has none
    if graphs[STATIC_FP32] is not None and not is_static(graph_metadata(graphs[STATIC_FP32])):
        raise DataError(f"--static-model {static} has a dynamic batch axis; export it with "
                        "`e3dpsm export --static-batch`")
    return graphs


def edge_graphs(paths: Sequence[str]) -> dict[str, Path]:
    """{"<runtime>/<precision>": path} of the --edge-models artifacts whose runtime is installed
    (the targets of a missing one are reported unavailable with the install line)."""
    from e3dpsm.profiles.targets import EDGE_RUNTIMES
    from e3dpsm.runtime.stepping import artifact_runtime, open_stepper
    from e3dpsm.utils.extras import missing_reason

    found: dict[str, Path] = {}
    for path in paths:
        runtime = artifact_runtime(_existing(path, "--edge-models"))
        if runtime not in EDGE_RUNTIMES:
            raise ConfigError(f"--edge-models takes .pte and .tflite artifacts; {path} runs on {runtime}")
        if missing_reason(EDGE_RUNTIMES[runtime][0]) is None:
            found[f"{runtime}/{open_stepper(path).artifact['precision']}"] = Path(path)
    return found


def _existing(path: str | None, flag: str) -> Path | None:
    if path is None:
        return None
    if not Path(path).is_file():
        raise DataError(f"{flag} {path} does not exist")
    return Path(path)


def is_static(meta: GraphMetadata) -> bool:
    return not isinstance(meta.frame_input["shape"][0], str)


def wants_static(targets: Sequence[Target]) -> bool:
    return any(t.static_batch for t in targets)


def export_fp32(model: Any, folder: Path) -> Path:
    from e3dpsm.export import export_step

    return export_step(model, folder / GRAPH_NAME)


def add_static_graph(model: Any, folder: Path, targets: Sequence[Target], graphs: Mapping[str, Path | None],
                     frames: np.ndarray, window_ms: float) -> dict[str, Path | None]:
    """`graphs` with the static-batch export of `model` in `folder` when a selected target
    wants one and none was given, parity-checked against `model` on the first `frames`."""
    from e3dpsm.export import export_step_with_report

    out = dict(graphs)
    if wants_static(targets) and out.get(STATIC_FP32) is None:
        out[STATIC_FP32] = Path(export_step_with_report(model, folder / STATIC_GRAPH_NAME, static_batch=True).path)
        check_static_graph(model, out[STATIC_FP32], frames[:STATIC_PARITY_STEPS], window_ms)
    return out


def check_static_graph(model: Any, path: Path, frames: np.ndarray, window_ms: float, tolerances: Any = None) -> Any:
    """The static export against the PyTorch model over carried steps (the project's parity
    tolerances: poses within 0.01 mm, states within 1e-4 of their scale); raises
    ValueMismatchError when it differs, so no verdict is ever drawn on a wrong graph."""
    from e3dpsm.export.parity import Tolerances, assert_parity, run_parity
    from e3dpsm.runtime.session import StepSession

    session = StepSession(path, threads=1, spin=False)
    report = run_parity(model, session, frames, window_ms, tolerances or Tolerances(), runtime="onnxruntime static")
    assert_parity(report)
    return report
