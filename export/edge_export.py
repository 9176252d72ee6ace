"""What the edge converters (ExecuTorch, LiteRT, Core ML) share: the same step wrapper the
ONNX exporter traces (states as explicit inputs and outputs, the window length an input),
exported for one stream (batch 1) with `torch.export`, and the state-layout metadata each
artifact carries (runtime/artifact_metadata.py), built from the model's `state_spec()`
through the same `graph_metadata` as the ONNX graph's."""
from __future__ import annotations

import contextlib
import importlib.metadata
from typing import Any, Iterator, Mapping

import torch
from torch import nn

from e3dpsm.export.spec import StepIOSpec, graph_metadata, step_io_spec
from e3dpsm.export.wrapper import StepGraph
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.layers.deformable import export_attention_form
from e3dpsm.models import E3DPSM
from e3dpsm.errors import ConfigError

EDGE_BATCH = 1  # one stream per artifact; runtime/artifact_session.py steps batches row by row
EDGE_ATTENTION_FORMS = ("grid_sample", "gather")  # DeformConv has no edge-runtime kernel


class NamedStepGraph(nn.Module):
    """`StepGraph` with named inputs (keyword arguments) and named outputs (a dict), so that
    converters that keep names (LiteRT signatures, Core ML) expose the ONNX graph's names."""

    def __init__(self, model: E3DPSM) -> None:
        super().__init__()
        self.step = StepGraph(model)
        self.spec = step_io_spec(model, EDGE_BATCH)

    def forward(self, **inputs: torch.Tensor) -> dict[str, torch.Tensor]:
        outputs = self.step(*(inputs[name] for name in self.spec.input_names))
        return dict(zip(self.spec.output_names, outputs))

    def example_kwargs(self) -> dict[str, torch.Tensor]:
        return dict(zip(self.spec.input_names, self.step.example_inputs(EDGE_BATCH)))


def check_attention_form(form: str) -> str:
    if form not in EDGE_ATTENTION_FORMS:
        raise ConfigError(f"attention form {form!r} is not available for edge runtimes; choose one of "
                          f"{', '.join(EDGE_ATTENTION_FORMS)}")
    return form


@contextlib.contextmanager
def export_ready(model: E3DPSM, attention_form: str) -> Iterator[E3DPSM]:
    """The model in eval mode with frozen parameters (so parameter-only products fold into
    constants) and the chosen attention form; everything restored on exit."""
    check_attention_form(attention_form)
    was_training = model.training
    grads = [p.requires_grad for p in model.parameters()]
    model.eval().requires_grad_(False)
    try:
        with torch.no_grad(), export_attention_form(model, sampler=attention_form,
                                                     fold_projections=attention_form != "grid_sample"):
            yield model
    finally:
        for param, grad in zip(model.parameters(), grads):
            param.requires_grad_(grad)
        model.train(was_training)


def step_spec(model: E3DPSM) -> StepIOSpec:
    return step_io_spec(model, EDGE_BATCH)


def converter_versions(*packages: str) -> dict[str, str | None]:
    versions: dict[str, str | None] = {}
    for name in ("torch", *packages):
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def artifact_contract(model: E3DPSM, fmt: str, precision: str, attention_form: str, packages: tuple[str, ...],
                      extra: Mapping[str, Any] | None = None) -> tuple[GraphMetadata, dict[str, Any]]:
    """(the ONNX graph's metadata for batch 1, the artifact record) of one converted artifact."""
    spec = step_spec(model)
    meta = graph_metadata(model, {"attention_form": attention_form, "format": fmt}, EDGE_BATCH)
    if precision != "fp32":
        # Where `quantize` puts an ONNX graph's mode: golden check picks its tolerance profile
        # (and an INT8 artifact's task budget) from it, as for a quantised ONNX graph.
        budget = (extra or {}).get("budget")
        meta = meta.with_quantization({"mode": precision, "format": fmt, **({"budget": budget} if budget else {})})
    record = {"format": fmt, "precision": precision, "attention_form": attention_form,
              "inputs": spec.input_names, "outputs": spec.output_names,
              "versions": converter_versions(*packages), **(extra or {})}
    return meta, record

