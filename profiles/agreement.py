"""Each CPU target's outside figure (profiles.outside) on exactly the graph, inputs and
compile properties the profile timed, and how the profile's own figure compares with it."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.profiles.inputs import Frames
from e3dpsm.profiles.latency import openvino_target_config
from e3dpsm.profiles.outside import (OutsideFigure, ort_profiler_figure, perf_test_path, run_benchmark_app,
                                     run_perf_test)
from e3dpsm.profiles.targets import Target

CPU_PROVIDERS = ("CPUExecutionProvider", "CPU", "cpu")


def outside_figure(target: Target, graph: Path | None, frames: Frames, seconds: float, work: Path,
                   ort_summary: Mapping[str, Any] | None) -> OutsideFigure:
    """The runtime's own timer for `target` (run under `work`), or why there is none."""
    if target.provider not in CPU_PROVIDERS:
        return OutsideFigure("-", reason="outside timers are run for CPU targets only")
    if target.runtime == "torch" or graph is None:
        return OutsideFigure("-", reason="no outside timer for PyTorch eager")
    meta = _metadata(graph)
    dynamic = isinstance(meta.frame_input["shape"][0], str)
    if target.runtime == "onnxruntime":
        if perf_test_path() is not None:
            return run_perf_test(graph, target.threads, seconds, dynamic, work)
        return ort_profiler_figure(ort_summary)
    stateful = target.runtime == "openvino-stateful"
    model = _openvino_ir(graph, stateful, work)
    inputs = {meta.frame_input["name"]: frames.lnes[0][None],
              meta.window_input["name"]: np.full((1,), frames.window_ms, np.float32)}
    if not stateful:  # the stateful IR starts from the initial states it holds
        inputs.update({s.input_name: s.initial_value(1) for s in meta.states})
    return run_benchmark_app(model, openvino_target_config(target), seconds, work, inputs, dynamic and not stateful)


def _metadata(graph: Path) -> GraphMetadata:
    import onnx

    return GraphMetadata.from_onnx(onnx.load(str(graph), load_external_data=False), source=str(graph))


def _openvino_ir(graph: Path, stateful: bool, work: Path) -> Path:
    """The graph as the profile's runner compiles it, saved as an IR: read with e3dpsm's
    operator rules (DeformConv), stateful ones made stateful at batch 1."""
    from e3dpsm.export.openvino_ir import convert_step_graph, save_ir

    model, _ = convert_step_graph(graph, stateful=stateful, batch=1 if stateful else None)
    work.mkdir(parents=True, exist_ok=True)
    xml, _ = save_ir(model, work / "step.xml")
    return xml


def agreement_ratio(profile_ms: float | None, outside: OutsideFigure) -> float | None:
    """The profile's figure over the outside tool's (1.0: they agree)."""
    if profile_ms is None or outside.p50_ms is None or outside.p50_ms <= 0:
        return None
    return profile_ms / outside.p50_ms
