"""What the edge converters share (export/edge_export.py), without converting anything: the
named step module against the positional one, the attention forms an edge artifact may use,
the model made export-ready and given back as it was, the converters' versions, and the
contract an artifact carries (the ONNX graph's metadata at batch 1, the quantisation entry
golden check reads, the record)."""
from __future__ import annotations

import importlib.metadata

import pytest
import torch

import e3dpsm
from _model_helpers import converter_tiny
from e3dpsm.errors import ConfigError
from e3dpsm.export import edge_export
from e3dpsm.export.edge_export import (EDGE_ATTENTION_FORMS, EDGE_BATCH, NamedStepGraph, artifact_contract,
                                       check_attention_form, converter_versions, export_ready, step_spec)
from e3dpsm.export.spec import graph_metadata, step_io_spec
from e3dpsm.export.wrapper import StepGraph
from e3dpsm.layers.deformable import DeformableTransformerBlock


@pytest.fixture(scope="module")
def model():
    return converter_tiny()


def test_the_named_step_module_is_the_positional_one_with_the_specs_names(model) -> None:
    named = NamedStepGraph(model)
    spec = step_io_spec(model, 1)
    assert EDGE_BATCH == 1 and named.spec == spec == step_spec(model)
    kwargs = named.example_kwargs()
    assert list(kwargs) == spec.input_names
    for value, expected in zip(kwargs.values(), StepGraph(model).example_inputs(1)):
        torch.testing.assert_close(value, expected, rtol=0, atol=0)
    g = torch.Generator().manual_seed(1)
    kwargs["lnes"] = (torch.rand(kwargs["lnes"].shape, generator=g) < 0.2).float()
    kwargs["window_ms"] = torch.tensor([33.0])
    with torch.no_grad():
        got = named(**dict(reversed(list(kwargs.items()))))  # by name, in any order
        expected = StepGraph(model)(*kwargs.values())
    assert list(got) == spec.output_names
    for value, reference in zip(got.values(), expected):
        torch.testing.assert_close(value, reference, rtol=0, atol=0)


def test_edge_artifacts_take_the_grid_sample_and_gather_forms_only() -> None:
    assert EDGE_ATTENTION_FORMS == ("grid_sample", "gather")
    for form in EDGE_ATTENTION_FORMS:
        assert check_attention_form(form) == form
    with pytest.raises(ConfigError) as error:
        check_attention_form("deform_conv")
    assert str(error.value) == ("attention form 'deform_conv' is not available for edge runtimes; choose one of "
                                "grid_sample, gather")


@pytest.mark.parametrize("form, fold", [("gather", True), ("grid_sample", False)])
def test_export_ready_freezes_and_sets_the_form_then_gives_everything_back(form, fold) -> None:
    model = e3dpsm.create_model("tiny", height=32, width=64).train()
    frozen = next(iter(model.parameters()))
    frozen.requires_grad_(False)  # a caller's own choice, restored as it was
    blocks = [m for m in model.modules() if isinstance(m, DeformableTransformerBlock)]
    before = [(b.attn.sampler, b.fold_projections) for b in blocks]
    assert blocks and before == [("grid_sample", False)] * len(blocks)  # the model's own form
    for block in blocks[:1]:  # one block set otherwise: each is put back as it was, not to a default
        block.attn.sampler, block.fold_projections = "gather", True
    before = [(b.attn.sampler, b.fold_projections) for b in blocks]
    with export_ready(model, form) as ready:
        assert ready is model and not model.training and not torch.is_grad_enabled()
        assert not any(p.requires_grad for p in model.parameters())
        assert [(b.attn.sampler, b.fold_projections) for b in blocks] == [(form, fold)] * len(blocks)
    assert model.training and torch.is_grad_enabled()
    assert [p.requires_grad for p in model.parameters()] == [False] + [True] * (len(list(model.parameters())) - 1)
    assert [(b.attn.sampler, b.fold_projections) for b in blocks] == before
    with pytest.raises(KeyError), export_ready(model, form):  # given back on an error too
        raise KeyError("x")
    assert model.training and [(b.attn.sampler, b.fold_projections) for b in blocks] == before
    with pytest.raises(ConfigError):
        with export_ready(model, "deform_conv"):
            pass
    assert model.training


def test_converter_versions_name_torch_first_and_none_for_what_is_missing() -> None:
    versions = converter_versions("onnx", "no-such-package-e3dpsm")
    assert list(versions) == ["torch", "onnx", "no-such-package-e3dpsm"]
    assert versions == {"torch": importlib.metadata.version("torch"), "onnx": importlib.metadata.version("onnx"),
                        "no-such-package-e3dpsm": None}


def test_an_fp32_artifacts_contract_is_the_onnx_graphs_at_batch_one(model, monkeypatch) -> None:
    monkeypatch.setattr(edge_export, "converter_versions", lambda *packages: {"packages": list(packages)})
    meta, record = artifact_contract(model, "litert", "fp32", "gather", ("litert_torch", "ai_edge_litert"),
                                     {"note": 1})
    assert meta == graph_metadata(model, {"attention_form": "gather", "format": "litert"}, 1)
    assert meta.quantization is None
    spec = step_io_spec(model, 1)
    assert record == {"format": "litert", "precision": "fp32", "attention_form": "gather",
                      "inputs": spec.input_names, "outputs": spec.output_names,
                      "versions": {"packages": ["litert_torch", "ai_edge_litert"]}, "note": 1}
    assert artifact_contract(model, "litert", "fp32", "gather", ())[1].keys() == record.keys() - {"note"}


@pytest.mark.parametrize("extra, quantization", [
    (None, {"mode": "int8", "format": "executorch"}),
    ({"budget": {"limit_pct": 1.0}}, {"mode": "int8", "format": "executorch", "budget": {"limit_pct": 1.0}}),
    ({"budget": None, "other": 2}, {"mode": "int8", "format": "executorch"}),
])
def test_a_quantised_artifact_says_its_mode_where_golden_check_reads_it(model, extra, quantization) -> None:
    meta, record = artifact_contract(model, "executorch", "int8", "grid_sample", ("executorch",), extra)
    assert meta.quantization == quantization
    assert record["precision"] == "int8" and set(record["versions"]) == {"torch", "executorch"}
    for key, value in (extra or {}).items():
        assert record[key] == value
