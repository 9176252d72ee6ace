"""`quantize --runtimes`: the budget checked on ONNX Runtime and OpenVINO, the worst counting."""
from __future__ import annotations

import json

import numpy as np
import onnx
import pytest

from _quantize_helpers import RECURRENT_FLOAT
from e3dpsm.cli import main
from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import ConfigError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.quantize import QuantizeOptions, quantize_graph
from e3dpsm.quantize import api
from e3dpsm.quantize.front_report import markdown_report, runtimes_clause
from e3dpsm.quantize.holdout import make_holdout
from e3dpsm.runtime.openvino_session import OpenVINOStepSession
from e3dpsm.validation.streams import onnx_stream_outputs

pytest.importorskip("openvino")


@pytest.mark.parametrize("runtimes", [(), ("tensorrt",), ("onnxruntime", "tflite")])
def test_unknown_or_no_runtime_is_refused(runtimes):
    with pytest.raises(ConfigError, match="runtime"):
        QuantizeOptions(runtimes=runtimes)


def test_openvino_refused_in_one_line_where_it_is_not_available(monkeypatch):
    from e3dpsm.runtime import openvino_session

    monkeypatch.setattr(openvino_session, "openvino_available", lambda: (False, "openvino is not installed (pip ...)"))
    with pytest.raises(ConfigError, match=r"^--runtimes openvino: openvino is not installed"):
        QuantizeOptions(runtimes=("onnxruntime", "openvino"))
    assert QuantizeOptions(runtimes=("onnxruntime",)).runtimes == ("onnxruntime",)  # not asked: not needed


def test_the_worst_runtime_counts(monkeypatch, tmp_path):
    measured = {"onnxruntime": 0.4, "openvino": 1.3}
    monkeypatch.setattr(api, "accuracy_of", lambda model, holdout, threads, runtime: {
        "bound_pct": measured[runtime], "mpjpe_mm": 10.0 + measured[runtime]})
    options = QuantizeOptions(runtimes=("onnxruntime", "openvino"))
    worst = api.worst_accuracy(tmp_path / "g.onnx", None, options)
    assert worst["runtime"] == "openvino" and worst["bound_pct"] == 1.3 and worst["mpjpe_mm"] == 11.3
    assert worst["bound_pct_by_runtime"] == measured
    measured["onnxruntime"] = 1.31
    assert api.worst_accuracy(tmp_path / "g.onnx", None, options)["runtime"] == "onnxruntime"
    only = api.worst_accuracy(tmp_path / "g.onnx", None, options, runtimes=["onnxruntime"])
    assert only["bound_pct_by_runtime"] == {"onnxruntime": 1.31}


def test_a_search_trial_counts_openvino_but_the_ranking_does_not(monkeypatch, tmp_path):
    """The evaluator the search probes with measures each trial on every runtime; the nodes
    search's ranking only orders nodes, on the first runtime alone."""
    asked = []
    monkeypatch.setattr(api, "accuracy_of", lambda model, holdout, threads, runtime: asked.append(runtime) or {
        "bound_pct": {"onnxruntime": 0.2, "openvino": 0.9}[runtime]})
    monkeypatch.setattr(api, "finalize", lambda *a, **k: None)
    monkeypatch.setattr(api, "save_model", lambda model, path: path.write_bytes(b""))
    options = QuantizeOptions(runtimes=("onnxruntime", "openvino"))
    trial = api._evaluator(None, None, options, tmp_path, lambda excluded: object())
    assert trial([], "t") == 0.9 and asked == ["onnxruntime", "openvino"]
    asked.clear()
    ranking = api._evaluator(None, None, options, tmp_path, lambda excluded: object(), runtimes=options.runtimes[:1])
    assert ranking([], "r") == 0.2 and asked == ["onnxruntime"]


def test_quantize_reports_the_budget_on_both_runtimes(tmp_path, trained_graph, quant_data):
    """The written graph measured on both: the report's distance is the larger, each runtime's
    figure matches a stream run here on that runtime (an independent loop over OpenVINO's
    own session), and report.md names both."""
    out = tmp_path / "int8"
    report = quantize_graph(trained_graph, quant_data, out,
                            QuantizeOptions(**{**RECURRENT_FLOAT, "runtimes": ("onnxruntime", "openvino")}))
    h = report["holdout"]
    assert set(h["bound_pct_by_runtime"]) == {"onnxruntime", "openvino"}
    assert h["bound_pct"] == max(h["bound_pct_by_runtime"].values())
    assert h["runtime"] == max(h["bound_pct_by_runtime"], key=h["bound_pct_by_runtime"].get)
    holdout = make_holdout(trained_graph, PreparedData.open(quant_data).split("val"), 20.0,
                           RECURRENT_FLOAT["holdout_frames"], 1)
    session = OpenVINOStepSession(out / "step_int8.onnx", threads=1, precision="f32")
    distances = []
    for name in ("pose", "pose_direct", "pose_delta"):
        ov = np.concatenate([onnx_stream_outputs(session, x, 20.0)[name] for x in holdout.lnes])
        fp32 = np.concatenate([o[name] for o in holdout.fp32_outputs])
        distances.append(np.linalg.norm(ov - fp32, axis=-1).mean())
    expected = 100.0 * max(distances) / holdout.budget_mpjpe
    assert h["bound_pct_by_runtime"]["openvino"] == pytest.approx(expected, rel=1e-4)
    # The graph says where its budget was checked (`golden check` compares it with its runtime).
    assert GraphMetadata.from_onnx(onnx.load(str(out / "step_int8.onnx"))).quantization["checked_on_runtimes"] == [
        "onnxruntime", "openvino"]
    md = (out / "report.md").read_text()
    assert "The worst of 2 runtimes (`--runtimes`): ONNX Runtime" in md and "OpenVINO" in md
    assert markdown_report(report) == md


def test_runtimes_clause_only_when_checked_on_more_than_one():
    assert runtimes_clause({"bound_pct_by_runtime": {"onnxruntime": 0.5}}) == ""
    assert runtimes_clause({}) == ""
    assert runtimes_clause({"bound_pct_by_runtime": {"onnxruntime": 0.4123, "openvino": 0.7456}}) == (
        " The worst of 2 runtimes (`--runtimes`): ONNX Runtime 0.412%, OpenVINO 0.746%.")


def test_cli_refuses_an_unknown_runtime(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["quantize", "--model", "m.onnx", "--data", "d", "--out", str(tmp_path / "q"), "--runtimes", "tflite"])
    assert exit_info.value.code == 2 and "invalid choice: 'tflite'" in capsys.readouterr().err
    assert not (tmp_path / "q").exists()


def test_pipeline_checks_every_quantised_budget_where_its_golden_check_runs(tmp_path, monkeypatch):
    """Each quantize stage checks its budget on the runtimes the golden check then runs it on:
    both where OpenVINO is installed, ONNX Runtime alone where it is not (where the golden
    check skips OpenVINO too), never a refusal that stops the pipeline."""
    from e3dpsm.cli import build_parser
    from e3dpsm.runtime import openvino_session
    from e3dpsm.pipeline.stages import STAGES, PipelineConfig

    quantize_stages = [s for s in STAGES if s.name.startswith("quantize-")]
    assert {s.name for s in quantize_stages} == {"quantize-int8", "quantize-fp16", "quantize-int8-dynamic"}
    for stage in quantize_stages:
        argv = stage.argv(PipelineConfig(out=tmp_path))
        assert build_parser().parse_args(argv).runtimes == ["onnxruntime", "openvino"], stage.name
        assert json.dumps(argv)  # argv is plain strings
    monkeypatch.setattr(openvino_session, "openvino_available", lambda: (False, "openvino is not installed"))
    for stage in quantize_stages:
        assert build_parser().parse_args(stage.argv(PipelineConfig(out=tmp_path))).runtimes == ["onnxruntime"]


def test_a_golden_check_says_when_the_budget_was_not_checked_on_its_runtime():
    from e3dpsm.golden.verify import budget_runtime_note, runtime_comparison

    both = {"mode": "int8", "checked_on_runtimes": ["onnxruntime", "openvino"]}
    one = {"mode": "int8", "checked_on_runtimes": ["onnxruntime"]}
    assert runtime_comparison(both, "openvino")["checked_here"] is True
    assert runtime_comparison(one, "onnxruntime")["checked_here"] is True
    assert runtime_comparison(one, "openvino") == {
        "runtime": "openvino", "budget_checked_on": ["onnxruntime"], "checked_here": False}
    assert runtime_comparison(one, "openvino-bf16")["checked_here"] is False  # quantize measures f32 only
    assert runtime_comparison(None, "openvino")["checked_here"] is None  # an fp32 graph has no budget
    assert runtime_comparison({"mode": "int8"}, "openvino")["checked_here"] is None  # older graphs: unknown
    assert budget_runtime_note(runtime_comparison(both, "openvino")) == ""
    assert budget_runtime_note(runtime_comparison(None, "openvino")) == ""
    note = budget_runtime_note(runtime_comparison(one, "openvino"))
    assert "checked on onnxruntime, not on openvino" in note and note.endswith("--runtimes onnxruntime openvino")
    assert "f32 only" in budget_runtime_note(runtime_comparison(one, "openvino-bf16"))
