"""Export the stateful single-step graph to ONNX: trace, attach metadata, simplify, check.

Every S5 state (real and imaginary parts) and the fusion state (pose, covariance,
initialised flag) are explicit inputs and outputs with paired names (`x_in` -> `x_out`);
the batch axis is dynamic (or fixed to 1 with `static_batch`); only default-domain operators
are allowed, so the same file runs on ONNX Runtime (CPU, CUDA, TensorRT) and OpenVINO.

Deformable attention exports in its literal GridSample form by default (portable to every
runtime). `attention_form="gather"` writes channels-last corner gathers and one weighted
MatMul; `attention_form="deform_conv"` one standard DeformConv node per block (opset >= 19),
the fastest on ONNX Runtime's CPU (1.09x the `paper` step, benchmarks/results/
deform_conv_paper.md). Both fold the block's projections and equal the literal form to
float32 round-off. DeformConv is not the default: OpenVINO's ONNX reader needs the rule
e3dpsm registers (runtime/openvino_session.py), and other runtimes' support varies.
"""
from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import onnx
import torch

from e3dpsm.errors import E3DPSMError
from e3dpsm.export.spec import StepIOSpec, graph_metadata, step_io_spec
from e3dpsm.export.wrapper import StepGraph
from e3dpsm.layers.deform_conv_sampling import DEFORM_CONV_MIN_OPSET
from e3dpsm.layers.deformable import SAMPLERS, export_attention_form
from e3dpsm.models import E3DPSM
from e3dpsm.onnx_constants import retile_constants
from e3dpsm.state import BATCH_AXIS, StateSpec, initial_states
from e3dpsm.utils.io import atomic_path

log = logging.getLogger(__name__)

DEFAULT_OPSET = 17  # GridSample needs >= 16; LayerNormalization is a single op from 17
MIN_OPSET = 17
# onnx 1.23 writes IR 14 by default; ONNX Runtime 1.31 reads up to 13. Opset 17-20 graphs
# need no newer IR than 8-10, so the exporter writes the lowest IR its opset allows.
_IR_FOR_OPSET = {17: 8, 18: 8, 19: 9, 20: 9, 21: 10}
ALLOWED_DOMAINS = ("", "ai.onnx")
# Of each output's scale: float32 round-off of a reordered graph, no more. Measured on a tiny
# model with randomised attention: every attention form's unsimplified graph is up to 1e-4 of
# the scale from PyTorch on the stage-4 S5 state, and onnxsim moved the DeformConv form's by
# 1.1e-5; a broken simplification moves outputs by orders more (tests/test_export.py).
SIMPLIFY_RTOL = 5e-5


class ExportError(E3DPSMError):
    """The graph could not be exported, checked or simplified."""


@dataclass
class ExportResult:
    path: str
    opset: int
    ir_version: int
    nodes_traced: int
    nodes_final: int
    simplified: bool
    bytes: int
    seconds_export: float
    seconds_simplify: float
    op_types: dict[str, int]
    attention_form: str = "grid_sample"
    static_batch: bool = False
    retiled_constants: dict[str, int] = field(default_factory=dict)  # onnx_constants.Retiled

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def op_histogram(model: onnx.ModelProto) -> dict[str, int]:
    """Node count per op type, most frequent first."""
    hist: dict[str, int] = {}
    for node in model.graph.node:
        hist[node.op_type] = hist.get(node.op_type, 0) + 1
    return dict(sorted(hist.items(), key=lambda kv: -kv[1]))


def foreign_ops(model: onnx.ModelProto) -> list[str]:
    """`domain::op` of every node outside the default ONNX domain (none allowed)."""
    return sorted({f"{n.domain}::{n.op_type}" for n in model.graph.node if n.domain not in ALLOWED_DOMAINS})


def check_graph(model: onnx.ModelProto) -> None:
    """Full checker, strict shape inference, default-domain operators only."""
    foreign = foreign_ops(model)
    if foreign:
        raise ExportError(f"graph uses non-standard operators {foreign}; only default-domain ONNX ops are allowed")
    try:
        onnx.checker.check_model(model, full_check=True)
        onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True, data_prop=True)
    except (onnx.checker.ValidationError, onnx.shape_inference.InferenceError) as exc:
        raise ExportError(f"exported graph fails the ONNX checker: {str(exc).splitlines()[0]}") from exc


def _simplify(model: onnx.ModelProto, spec: StepIOSpec, states: tuple[StateSpec, ...], window_ms: float) -> onnx.ModelProto:
    """onnxsim, then our own check of the result on realistic inputs (two carried steps).

    onnxsim's own check (`check_n`) feeds uniform random inputs, window lengths and states and
    compares with a tolerance made for unit-scale outputs: poses of metre scale in mm fail it
    by round-off, or pass it with states the step never sees."""
    import onnxsim

    test_shapes = {t.name: [1 if isinstance(d, str) else d for d in t.shape] for t in spec.inputs}
    simplified, _ = onnxsim.simplify(model, check_n=0, test_input_shapes=test_shapes)
    worst = _max_relative_difference(model, simplified, spec, states, window_ms)
    if not worst[1] <= SIMPLIFY_RTOL:
        raise ExportError(f"onnxsim changed output {worst[0]} by {worst[1]:.1e} of its scale (limit "
                          f"{SIMPLIFY_RTOL:.0e}); export with --no-simplify")
    return simplified


def _max_relative_difference(
    a: onnx.ModelProto, b: onnx.ModelProto, spec: StepIOSpec, states: tuple[StateSpec, ...], window_ms: float,
) -> tuple[str, float]:
    """(output, max |a - b| / max |a|) over two carried steps on a sparse LNES-like frame."""
    import numpy as np
    import onnxruntime as ort

    sessions = [ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]) for m in (a, b)]
    frame_shape = [1, *spec.inputs[0].shape[1:]]
    rng = np.random.default_rng(0)
    frame = ((rng.random(frame_shape) < 0.05) * rng.random(frame_shape)).astype(np.float32)
    feeds = {spec.inputs[1].name: np.array([window_ms], np.float32),
             **{s.input_name: v for s, v in zip(states, initial_states(states, 1).values())}}
    worst = ("", 0.0)
    for _ in range(2):
        results = [dict(zip(spec.output_names, sess.run(spec.output_names, {spec.inputs[0].name: frame, **feeds})))
                   for sess in sessions]
        for name in spec.output_names:
            ref, got = results[0][name].astype(np.float64), results[1][name].astype(np.float64)
            rel = float(np.max(np.abs(got - ref)) / max(float(np.max(np.abs(ref))), 1e-6)) if ref.size else 0.0
            worst = max(worst, (name, rel), key=lambda w: w[1])
        feeds.update({s.input_name: results[0][s.output_name] for s in states})
    return worst


@contextlib.contextmanager
def _eval_mode(model: torch.nn.Module):
    was_training = model.training
    model.eval()
    try:
        yield model
    finally:
        model.train(was_training)


def export_step_with_report(
    model: E3DPSM, path: str | os.PathLike, opset: int | None = None, simplify: bool = True,
    metadata_extra: dict[str, Any] | None = None, attention_form: str = "grid_sample", static_batch: bool = False,
) -> ExportResult:
    """`attention_form`: "grid_sample" (the literal form), "gather" or "deform_conv" (export
    forms, folded projections); `static_batch`: fix the batch axis to 1 (fewer shape ops, for
    single-stream devices). `opset` defaults to the lowest the form needs (17; 19 for DeformConv)."""
    if attention_form not in SAMPLERS:
        raise ExportError(f"unknown attention form {attention_form!r}; choose from {SAMPLERS}")
    min_opset = DEFORM_CONV_MIN_OPSET if attention_form == "deform_conv" else MIN_OPSET
    opset = opset or max(DEFAULT_OPSET, min_opset)
    if opset not in _IR_FOR_OPSET:
        raise ExportError(f"opset {opset} is not supported; use one of {sorted(_IR_FOR_OPSET)}")
    if opset < min_opset:
        raise ExportError(f"attention form {attention_form!r} needs opset >= {min_opset} (ONNX DeformConv); "
                          f"pass --opset {min_opset} or leave --opset out")
    batch = 1 if static_batch else BATCH_AXIS
    spec = step_io_spec(model, batch)
    wrapper = StepGraph(model)
    t0 = time.perf_counter()
    with _eval_mode(model), torch.no_grad(), tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings(), \
            export_attention_form(model, sampler=attention_form, fold_projections=attention_form != "grid_sample"):
        # Shape checks in `step` are Python-level and trace to constants: expected.
        warnings.simplefilter("ignore", category=torch.jit.TracerWarning)
        warnings.simplefilter("ignore", category=DeprecationWarning)
        raw = Path(tmp) / "step.onnx"
        torch.onnx.export(
            wrapper, wrapper.example_inputs(1), str(raw), input_names=spec.input_names,
            output_names=spec.output_names, dynamic_axes=spec.dynamic_axes, opset_version=opset,
            do_constant_folding=True, dynamo=False,
        )
        graph = onnx.load(str(raw))
    seconds_export = time.perf_counter() - t0
    nodes_traced = len(graph.graph.node)

    t1 = time.perf_counter()
    if simplify:
        graph = _simplify(graph, spec, model.state_spec(), model.config.train_window_ms)
    seconds_simplify = time.perf_counter() - t1
    # The interface is the spec's: the tracer leaves output axes symbolic ("Addpose_direct_dim_1")
    # and onnxsim renamed window_ms's "batch" axis "unk__0" (the graph broadcasts a window of 1).
    spec.declare_on(graph)
    # After simplifying: onnxsim would fold the Tiles back. Exact (onnx_constants.py).
    retiled = retile_constants(graph)

    graph.ir_version = _IR_FOR_OPSET[opset]
    graph_metadata(model, {"attention_form": attention_form, **(metadata_extra or {})}, batch).write_to(graph)
    graph.producer_name = "e3dpsm"
    graph.doc_string = f"E-3DPSM single-step graph, variant {model.config.variant}"
    check_graph(graph)
    # The graph must expose exactly the spec's names, in its order.
    got_in = [i.name for i in graph.graph.input]
    got_out = [o.name for o in graph.graph.output]
    if got_in != spec.input_names or got_out != spec.output_names:
        raise ExportError(f"exported names differ from the spec: inputs {got_in}, outputs {got_out}")

    with atomic_path(path, suffix=".onnx") as tmp_path:
        onnx.save(graph, str(tmp_path))
    size = Path(path).stat().st_size
    log.debug("exported %s: %d -> %d nodes, %.1f MB", path, nodes_traced, len(graph.graph.node), size / 1e6)
    return ExportResult(
        path=str(path), opset=opset, ir_version=graph.ir_version, nodes_traced=nodes_traced,
        nodes_final=len(graph.graph.node), simplified=simplify, bytes=size,
        seconds_export=round(seconds_export, 3), seconds_simplify=round(seconds_simplify, 3),
        op_types=op_histogram(graph), attention_form=attention_form, static_batch=static_batch,
        retiled_constants=retiled.to_dict(),
    )


def export_step(model: E3DPSM, path: str | os.PathLike, opset: int | None = None) -> Path:
    """Write the simplified, checked single-step graph of `model` to `path`."""
    return Path(export_step_with_report(model, path, opset).path)
