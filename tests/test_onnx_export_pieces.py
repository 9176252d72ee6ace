"""The pieces of the ONNX exporter (export/onnx_export.py), fast: the op histogram, the
foreign-operator and checker gates, the opset and form refusals before anything is traced,
the simplifier's own check at its tolerance (a graph moved just inside and just outside it),
and what one export of the tiny writes and reports. Parity of exported graphs with PyTorch is
tests/test_export.py's."""
from __future__ import annotations

import copy

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper

import e3dpsm
from _io_helpers import record_temporaries
from e3dpsm.export import onnx_export
from e3dpsm.export.onnx_export import (SIMPLIFY_RTOL, ExportError, check_graph, export_step_with_report,
                                       foreign_ops, op_histogram)
from e3dpsm.export.spec import step_io_spec
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.layers.deformable import SAMPLERS


def _graph(nodes, inputs=("a",), outputs=("y",), shape=(2, 3)) -> onnx.ModelProto:
    graph = helper.make_graph(
        nodes, "g", [helper.make_tensor_value_info(n, TensorProto.FLOAT, list(shape)) for n in inputs],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, list(shape)) for n in outputs])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid("com.microsoft", 1),
                                                    helper.make_opsetid("custom", 1)])
    model.ir_version = 8
    return model


def test_the_histogram_counts_each_op_type_most_frequent_first() -> None:
    kinds = ["Relu", "Add", "Mul", "Add", "Mul", "Add", "Sigmoid"]
    nodes = [helper.make_node(k, ["a"] if k in ("Relu", "Sigmoid") else ["a", "a"], [f"t{i}"]) for i, k in enumerate(kinds)]
    histogram = op_histogram(_graph(nodes))
    assert list(histogram.items()) == [("Add", 3), ("Mul", 2), ("Relu", 1), ("Sigmoid", 1)]  # ties: first seen first


def test_foreign_operators_are_listed_once_each_and_refused() -> None:
    nodes = [helper.make_node("FusedConv", ["a"], ["b"], domain="com.microsoft"),
             helper.make_node("Relu", ["b"], ["c"], domain="ai.onnx"),
             helper.make_node("X", ["c"], ["d"], domain="custom"),
             helper.make_node("FusedConv", ["d"], ["y"], domain="com.microsoft")]
    model = _graph(nodes)
    assert foreign_ops(model) == ["com.microsoft::FusedConv", "custom::X"]
    with pytest.raises(ExportError) as error:
        check_graph(model)
    assert str(error.value) == ("graph uses non-standard operators ['com.microsoft::FusedConv', 'custom::X']; only "
                                "default-domain ONNX ops are allowed")


@pytest.mark.parametrize("nodes, inputs", [
    ([helper.make_node("Add", ["a", "missing"], ["y"])], ("a",)),  # the checker: an input nobody makes
    ([helper.make_node("MatMul", ["a", "b"], ["y"])], ("a", "b")),  # strict shape inference: [2,3] x [2,3]
])
def test_a_graph_the_checker_refuses_is_one_line(nodes, inputs) -> None:
    with pytest.raises(ExportError) as error:
        check_graph(_graph(nodes, inputs))
    assert str(error.value).startswith("exported graph fails the ONNX checker: ") and "\n" not in str(error.value)


def test_a_valid_graph_passes_the_checks() -> None:
    check_graph(_graph([helper.make_node("Add", ["a", "b"], ["y"])], ("a", "b")))


@pytest.mark.parametrize("options, message", [
    ({"attention_form": "nope"}, f"unknown attention form 'nope'; choose from {SAMPLERS}"),
    ({"opset": 16}, "opset 16 is not supported; use one of [17, 18, 19, 20, 21]"),
    ({"opset": 22}, "opset 22 is not supported; use one of [17, 18, 19, 20, 21]"),
    ({"attention_form": "deform_conv", "opset": 18},
     "attention form 'deform_conv' needs opset >= 19 (ONNX DeformConv); pass --opset 19 or leave --opset out"),
])
def test_bad_options_are_refused_before_tracing(tmp_path, monkeypatch, options, message) -> None:
    monkeypatch.setattr(onnx_export, "StepGraph", lambda *_: pytest.fail("traced"))
    with pytest.raises(ExportError) as error:
        export_step_with_report(e3dpsm.create_model("tiny"), tmp_path / "x.onnx", **options)
    assert str(error.value) == message and list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def tiny():
    return e3dpsm.create_model("tiny")


@pytest.fixture(scope="module")
def exported(tiny, tmp_path_factory):
    """One export of the tiny in train mode (the exporter must trace it in eval and put it back)."""
    path = tmp_path_factory.mktemp("export") / "sub" / "step.onnx"
    tiny.train()
    result = export_step_with_report(tiny, path, metadata_extra={"note": "kept"})
    modes = {m.training for m in tiny.modules()}
    return result, path, modes


def test_an_export_writes_the_checked_graph_and_reports_it(tiny, exported) -> None:
    result, path, modes = exported
    assert modes == {True}  # every module back in train mode
    graph = onnx.load(str(path))
    spec = step_io_spec(tiny)
    assert [i.name for i in graph.graph.input] == spec.input_names
    assert [o.name for o in graph.graph.output] == spec.output_names
    assert graph.graph.input[0].type.tensor_type.shape.dim[0].dim_param == "batch"
    assert (graph.ir_version, graph.producer_name, graph.doc_string) == (8, "e3dpsm", "E-3DPSM single-step graph, variant tiny")
    assert {o.domain for o in graph.opset_import} <= {"", "ai.onnx"} and graph.opset_import[0].version == 17
    meta = GraphMetadata.from_onnx(graph)
    assert (meta.config["attention_form"], meta.config["note"], meta.config["variant"]) == ("grid_sample", "kept", "tiny")
    assert "static_batch" not in meta.config
    assert result.path == str(path) and result.bytes == path.stat().st_size
    assert (result.opset, result.ir_version, result.simplified, result.static_batch) == (17, 8, True, False)
    assert result.attention_form == "grid_sample" and result.op_types == op_histogram(graph)
    assert result.nodes_final == len(graph.graph.node) < result.nodes_traced
    for seconds in (result.seconds_export, result.seconds_simplify):
        assert 0 < seconds == round(seconds, 3)
    assert result.to_dict()["retiled_constants"] == result.retiled_constants
    assert [p.name for p in path.parent.iterdir()] == ["step.onnx"]  # no temporary left beside it


def test_a_static_deform_conv_export_takes_opset_19_and_its_ir(tiny, tmp_path, monkeypatch) -> None:
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)  # the trace goes to a temporary folder, nothing to the working one
    temporaries = record_temporaries(monkeypatch, onnx_export)
    result = export_step_with_report(tiny, tmp_path / "d.onnx", simplify=False, attention_form="deform_conv",
                                     static_batch=True)
    assert list(work.iterdir()) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["cwd", "d.onnx"]
    assert len(temporaries) == 1 and temporaries[0].startswith(".d.onnx.") and temporaries[0].endswith(".onnx")
    # a leftover temporary is hidden and keeps the graph's extension
    assert 0 < result.seconds_export < 600
    graph = onnx.load(str(tmp_path / "d.onnx"))
    assert (result.opset, result.ir_version, graph.ir_version, result.simplified) == (19, 9, 9, False)
    assert result.nodes_final == result.nodes_traced and result.seconds_simplify < 0.05
    assert result.op_types.get("DeformConv", 0) > 0 and result.static_batch
    assert graph.graph.input[0].type.tensor_type.shape.dim[0].dim_value == 1
    assert GraphMetadata.from_onnx(graph).config["static_batch"] == 1


def _scaled_output(model: onnx.ModelProto, output: str, factor: float) -> onnx.ModelProto:
    """`model` with one output multiplied by `factor` (the rest untouched)."""
    moved = copy.deepcopy(model)
    for node in moved.graph.node:
        node.output[:] = [f"{o}_before" if o == output else o for o in node.output]
        node.input[:] = [f"{i}_before" if i == output else i for i in node.input]
    moved.graph.initializer.append(onnx.numpy_helper.from_array(np.float32(factor), f"{output}_factor"))
    moved.graph.node.append(helper.make_node("Mul", [f"{output}_before", f"{output}_factor"], [output]))
    return moved


@pytest.fixture(scope="module")
def unsimplified(tiny, tmp_path_factory):
    path = tmp_path_factory.mktemp("raw") / "raw.onnx"
    tiny.eval()
    export_step_with_report(tiny, path, simplify=False)
    return onnx.load(str(path))


@pytest.mark.parametrize("output_index", [-1, 3], ids=["flag", "s5_state"])
@pytest.mark.parametrize("relative, passes", [(0.8 * SIMPLIFY_RTOL, True), (1.2 * SIMPLIFY_RTOL, False)])
def test_the_simplifiers_result_is_held_to_its_tolerance(tiny, unsimplified, monkeypatch, relative, passes,
                                                         output_index) -> None:
    """Relative to each output's own scale: the initialised flag (1.0) and the first S5 state
    (a few hundredths), both carried into the second step by the reference."""
    import onnxsim

    spec = step_io_spec(tiny)
    output = spec.output_names[output_index]
    assert output in {s.output_name for s in tiny.state_spec()}
    moved = _scaled_output(unsimplified, output, 1 + relative)
    monkeypatch.setattr(onnxsim, "simplify", lambda model, **kwargs: (moved, True))
    worst = onnx_export._max_relative_difference(unsimplified, moved, spec, tiny.state_spec(), 20.0)
    assert worst[0] == output and worst[1] == pytest.approx(relative, rel=0.02)
    if passes:
        assert onnx_export._simplify(unsimplified, spec, tiny.state_spec(), 20.0) is moved
        return
    with pytest.raises(ExportError) as error:
        onnx_export._simplify(unsimplified, spec, tiny.state_spec(), 20.0)
    assert str(error.value) == (f"onnxsim changed output {output} by {worst[1]:.1e} of its scale (limit 5e-05); "
                                "export with --no-simplify")


def test_identical_graphs_differ_by_nothing(tiny, unsimplified) -> None:
    spec = step_io_spec(tiny)
    assert onnx_export._max_relative_difference(unsimplified, unsimplified, spec, tiny.state_spec(), 20.0) == ("", 0.0)


def test_each_opset_is_written_with_the_lowest_ir_that_holds_it() -> None:
    # onnx's own table is the reference: ONNX Runtime 1.31 reads IR up to 13, onnx 1.23 writes 14.
    for opset, ir in onnx_export._IR_FOR_OPSET.items():
        assert ir == helper.find_min_ir_version_for([helper.make_opsetid("", opset)]) <= 13, opset
    assert sorted(onnx_export._IR_FOR_OPSET) == [17, 18, 19, 20, 21]


def test_the_results_defaults_are_the_plain_exports() -> None:
    result = onnx_export.ExportResult(path="p", opset=17, ir_version=8, nodes_traced=2, nodes_final=1,
                                      simplified=True, bytes=3, seconds_export=0.5, seconds_simplify=0.25, op_types={})
    assert (result.attention_form, result.static_batch, result.retiled_constants) == ("grid_sample", False, {})


def test_onnxsim_is_asked_for_no_check_of_its_own_on_one_stream(tiny, unsimplified, monkeypatch) -> None:
    import onnxsim

    calls = []
    monkeypatch.setattr(onnxsim, "simplify", lambda model, **kwargs: calls.append(kwargs) or (model, True))
    spec = step_io_spec(tiny)
    onnx_export._simplify(unsimplified, spec, tiny.state_spec(), 20.0)
    (kwargs,) = calls
    assert kwargs["check_n"] == 0  # its random-input check fails mm-scale poses by round-off (module docstring)
    assert kwargs["test_input_shapes"] == {t.name: [1, *t.shape[1:]] for t in spec.inputs}


def test_a_change_of_exactly_the_tolerance_passes(tiny, unsimplified, monkeypatch) -> None:
    import onnxsim

    monkeypatch.setattr(onnxsim, "simplify", lambda model, **kwargs: (model, True))
    monkeypatch.setattr(onnx_export, "_max_relative_difference", lambda *a: ("pose", SIMPLIFY_RTOL))
    assert onnx_export._simplify(unsimplified, step_io_spec(tiny), tiny.state_spec(), 20.0) is unsimplified
    monkeypatch.setattr(onnx_export, "_max_relative_difference", lambda *a: ("pose", float("nan")))
    with pytest.raises(ExportError, match="onnxsim changed output pose by nan"):  # NaN is never within
        onnx_export._simplify(unsimplified, step_io_spec(tiny), tiny.state_spec(), 20.0)


def test_the_literal_form_is_exported_unfolded(tiny, tmp_path, monkeypatch) -> None:
    """The grid_sample form keeps the block's projections as the model has them; the other forms
    fold them (export_attention_form). The same export with the folding forced differs."""
    literal = export_step_with_report(tiny, tmp_path / "literal.onnx", simplify=False)
    real = onnx_export.export_attention_form
    monkeypatch.setattr(onnx_export, "export_attention_form",
                        lambda model, sampler, fold_projections: real(model, sampler=sampler, fold_projections=True))
    folded = export_step_with_report(tiny, tmp_path / "folded.onnx", simplify=False)
    assert literal.op_types != folded.op_types


def test_the_trace_folds_constants(tiny, tmp_path, monkeypatch) -> None:
    """torch's own constant folding at trace time: without it the traced graph is larger."""
    folded = export_step_with_report(tiny, tmp_path / "folded.onnx", simplify=False)
    real_export = torch.onnx.export

    def unfolded_export(*args, **kwargs):
        return real_export(*args, **{**kwargs, "do_constant_folding": False})

    monkeypatch.setattr(torch.onnx, "export", unfolded_export)
    unfolded = export_step_with_report(tiny, tmp_path / "unfolded.onnx", simplify=False)
    assert folded.nodes_traced < unfolded.nodes_traced


def test_a_graph_whose_names_differ_from_the_spec_is_refused(tiny, tmp_path, monkeypatch) -> None:
    from e3dpsm.export.spec import StepIOSpec

    real_declare = StepIOSpec.declare_on

    def declare_and_rename(self, model):
        real_declare(self, model)
        model.graph.output[0].name = "renamed"

    monkeypatch.setattr(StepIOSpec, "declare_on", declare_and_rename)
    monkeypatch.setattr(onnx_export, "check_graph", lambda graph: None)  # the renamed output reads nothing
    with pytest.raises(ExportError) as error:
        export_step_with_report(tiny, tmp_path / "x.onnx", simplify=False)
    spec = step_io_spec(tiny)
    assert str(error.value) == (f"exported names differ from the spec: inputs {spec.input_names}, outputs "
                                f"{['renamed', *spec.output_names[1:]]}")
    assert not (tmp_path / "x.onnx").exists()


def test_the_simplifiers_probe_is_two_carried_steps_of_a_sparse_frame(tiny, unsimplified, monkeypatch) -> None:
    """What _max_relative_difference feeds both graphs: one stream, the training window, a sparse
    LNES-like frame (values in [0, 1), about 5% of the pixels), the initial states, then the
    reference's states for the second step; on ONNX Runtime's CPU provider."""
    import onnxruntime as ort

    real_session = ort.InferenceSession
    sessions = []

    class Recording:
        def __init__(self, model, providers):
            assert providers == ["CPUExecutionProvider"]
            self.inner, self.feeds, self.outputs = real_session(model, providers=providers), [], []
            sessions.append(self)

        def run(self, names, feeds):
            self.feeds.append({k: v.copy() for k, v in feeds.items()})
            self.outputs.append(self.inner.run(names, feeds))
            return self.outputs[-1]

    monkeypatch.setattr(ort, "InferenceSession", Recording)
    spec, states = step_io_spec(tiny), tiny.state_spec()
    moved = _scaled_output(unsimplified, states[0].output_name, 2.0)  # its states are not the reference's
    onnx_export._max_relative_difference(unsimplified, moved, spec, states, 25.0)
    assert len(sessions) == 2 and [len(s.feeds) for s in sessions] == [2, 2]
    frame = sessions[0].feeds[0]["lnes"]
    assert frame.shape == (1, *spec.inputs[0].shape[1:]) and frame.dtype == np.float32
    assert frame.min() >= 0 and frame.max() < 1 and 0.03 < np.count_nonzero(frame) / frame.size < 0.07
    from e3dpsm.state import initial_states

    for session in sessions:
        first, second = session.feeds
        assert first["window_ms"].tolist() == [25.0] and np.array_equal(first["lnes"], second["lnes"])
        for s, value in zip(states, initial_states(states, 1).values()):
            np.testing.assert_array_equal(first[s.input_name], value)
        reference = dict(zip(spec.output_names, sessions[0].outputs[0]))
        for s in states:
            np.testing.assert_array_equal(second[s.input_name], reference[s.output_name])
