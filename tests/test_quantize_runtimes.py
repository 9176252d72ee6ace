"""`quantize --runtimes`: the budget checked on ONNX Runtime and OpenVINO, the worst counting."""
from __future__ import annotations

import json

import numpy as np
import onnx
import pytest

from _quantize_helpers import fast
from e3dpsm.budget import BudgetCheck, MetricChange, TaskBudget, check_budget
from e3dpsm.cli import main
from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import ConfigError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.quantize import QuantizeOptions, quantize_graph
from e3dpsm.quantize.holdout import Judgement
from e3dpsm.runtime import StepSession
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


def _check(upper_pct: float) -> BudgetCheck:
    metric = MetricChange("mpjpe", 100.0, 100.0 + upper_pct, upper_pct, upper_pct, upper_pct, 0.0, 1.0)
    return BudgetCheck((metric,), 10, 1, upper_pct, TaskBudget())


def test_the_worst_runtime_counts():
    judged = Judgement({"onnxruntime": _check(0.4), "openvino": _check(1.3)})
    assert judged.worst is judged.by_runtime["openvino"] and judged.worst_share == pytest.approx(1.3)
    assert not judged.within and judged.to_dict()["by_runtime"]["onnxruntime"]["within"]
    assert Judgement({"onnxruntime": _check(1.0), "openvino": _check(0.2)}).within  # inclusive, both
    assert Judgement({"onnxruntime": _check(1.31), "openvino": _check(1.3)}).worst.metrics[0].upper_pct == 1.31


def test_quantize_reports_the_budget_on_both_runtimes(tmp_path, trained_graph, quant_data):
    """The written graph is checked on both; OpenVINO's figures match an independent loop over
    its own session on the held-out split; the metadata names both; report.md shows both."""
    out = tmp_path / "int8"
    report = quantize_graph(trained_graph, quant_data, out,
                            fast(mode="int8", exclude="recurrent", runtimes=("onnxruntime", "openvino")))
    by_runtime = report["check"]["by_runtime"]
    assert set(by_runtime) == {"onnxruntime", "openvino"}
    assert report["check"]["within"] == all(c["within"] for c in by_runtime.values())
    seq = PreparedData.open(quant_data).split("test")[0]
    gt = np.asarray(seq.j3d_mm, np.float32)
    x = np.asarray(seq.lnes, np.float32)
    fp32 = onnx_stream_outputs(StepSession(trained_graph, threads=1), x, 20.0)["pose"]
    ov = onnx_stream_outputs(OpenVINOStepSession(out / "step_int8.onnx", threads=1, precision="f32"), x, 20.0)["pose"]
    expected = check_budget([ov], [fp32], [gt])
    got = by_runtime["openvino"]["metrics"]
    for metric in expected.metrics:
        assert got[metric.name]["change_pct"] == pytest.approx(metric.change_pct, rel=1e-4, abs=1e-6)
    assert by_runtime["openvino"]["fidelity_mm"] == pytest.approx(expected.fidelity_mm, rel=1e-4)
    meta = GraphMetadata.from_onnx(onnx.load(str(out / "step_int8.onnx")))
    assert meta.quantization["checked_on_runtimes"] == ["onnxruntime", "openvino"]
    assert set(report["verdict"]["timings"]) == {"onnxruntime", "openvino"}
    md = (out / "report.md").read_text()
    assert "onnxruntime: distance to the fp32 poses" in md and "openvino: distance to the fp32 poses" in md


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
