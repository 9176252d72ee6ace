"""What `golden check` decides before it steps a graph (e3dpsm/golden/verify.py): the runtime an
artifact is checked on, the tolerance profile, the task budget, and the ISA and runtime notes the
report carries, each against hand-written expectations and every refusal compared whole."""
from __future__ import annotations

import pytest

from e3dpsm.budget import TaskBudget
from e3dpsm.errors import InputError
from e3dpsm.golden import verify
from e3dpsm.golden.tolerances import PROFILES
from e3dpsm.utils.isa import detect_isa


@pytest.mark.parametrize("model, runtime, checked_on", [
    ("g.onnx", "onnxruntime", "onnxruntime"), ("g.onnx", "openvino", "openvino"),
    ("g.onnx", "openvino-bf16", "openvino-bf16"), ("a/step.pte", "onnxruntime", "executorch"),
    ("a/step.pte", "executorch", "executorch"), ("step.tflite", "onnxruntime", "litert"),
])
def test_an_artifact_is_checked_on_its_own_runtime(model, runtime, checked_on) -> None:
    assert verify.artifact_check_runtime(model, runtime) == checked_on


def test_an_artifact_on_another_runtime_is_refused() -> None:
    with pytest.raises(InputError) as refused:
        verify.artifact_check_runtime("a/step.pte", "openvino")
    assert str(refused.value) == "a/step.pte runs on executorch, not openvino; leave --runtime out for it"


@pytest.mark.parametrize("quantization, runtime, name", [
    (None, "onnxruntime", "fp32"), (None, "openvino-bf16", "bf16"), ({"mode": "int8"}, "onnxruntime", "int8"),
    ({"mode": "int8"}, "openvino-bf16", "int8"), ({"mode": "fp16"}, "onnxruntime", "fp16"),
])
def test_the_default_profile_follows_the_graph_and_the_runtime(quantization, runtime, name) -> None:
    assert verify.resolve_profile(None, quantization, {}, runtime) == PROFILES[name]


def test_a_named_profile_takes_the_goldens_recorded_values() -> None:
    assert verify.resolve_profile("int8", None, {}) == PROFILES["int8"]
    recorded = {**PROFILES["fp32"].to_dict(), "pose_atol_mm": 0.5}
    chosen = verify.resolve_profile("fp32", None, {"tolerances": {"fp32": recorded, "int8": {}}})
    assert chosen.to_dict() == recorded and chosen != PROFILES["fp32"]
    assert verify.resolve_profile("int8", None, {"tolerances": {"int8": {}}}) == PROFILES["int8"]  # empty: defaults


def test_an_unknown_profile_is_refused() -> None:
    with pytest.raises(InputError) as refused:
        verify.resolve_profile("int4", None, {})
    assert str(refused.value) == f"unknown profile 'int4'; choose one of {', '.join(PROFILES)}"


def test_the_budget_comes_from_the_option_the_metadata_or_the_default() -> None:
    assert verify.resolve_budget(None) == TaskBudget()
    assert verify.resolve_budget({"mode": "int8"}) == TaskBudget()
    carried = {"budget": {"mpjpe_pct": 2.0, "jitter_pct": 7.0, "written_by": "quantize"}}  # unknown keys ignored
    assert verify.resolve_budget(carried) == TaskBudget(mpjpe_pct=2.0, jitter_pct=7.0)
    assert verify.resolve_budget(carried, 0.5) == TaskBudget(mpjpe_pct=0.5, pa_mpjpe_pct=0.5, jitter_pct=7.0)
    assert verify.resolve_budget(None, 3.0) == TaskBudget(mpjpe_pct=3.0, pa_mpjpe_pct=3.0)


def test_the_isa_comparison() -> None:
    host = detect_isa().to_dict()
    assert verify.isa_comparison(None) == {"host": host, "budget_checked_on": None, "same_kind": None}
    same = {"kind": host["kind"], "flags": []}
    assert verify.isa_comparison({"checked_on_isa": same}) == {"host": host, "budget_checked_on": same,
                                                               "same_kind": True}
    other = {"kind": "not-" + host["kind"]}
    assert verify.isa_comparison({"checked_on_isa": other})["same_kind"] is False


def test_the_runtime_comparison_and_its_note() -> None:
    assert verify.runtime_comparison(None, "openvino") == {"runtime": "openvino", "budget_checked_on": None,
                                                           "checked_here": None}
    here = verify.runtime_comparison({"checked_on_runtimes": ["onnxruntime", "openvino"]}, "openvino")
    assert here["checked_here"] is True and verify.budget_runtime_note(here) == ""
    assert verify.budget_runtime_note(verify.runtime_comparison(None, "openvino")) == ""
    elsewhere = verify.runtime_comparison({"checked_on_runtimes": ["onnxruntime"]}, "openvino")
    assert elsewhere == {"runtime": "openvino", "budget_checked_on": ["onnxruntime"], "checked_here": False}
    assert verify.budget_runtime_note(elsewhere) == (
        "the graph's budget was checked on onnxruntime, not on openvino: one quantised graph's error differs "
        "between runtimes; to hold it here, quantize with --runtimes onnxruntime openvino")
    bf16 = verify.runtime_comparison({"checked_on_runtimes": ["onnxruntime", "openvino"]}, "openvino-bf16")
    assert verify.budget_runtime_note(bf16) == (
        "the graph's budget was checked on onnxruntime and openvino, not on openvino-bf16: one quantised graph's "
        "error differs between runtimes; quantize checks budgets in f32 only")


def test_providers_apply_to_onnx_runtime_only(tmp_path) -> None:
    with pytest.raises(InputError) as openvino:
        verify.open_runner("g.onnx", "openvino", providers=["CPUExecutionProvider"])
    assert str(openvino.value) == "--providers applies to onnxruntime; OpenVINO runs on its CPU device here"
    with pytest.raises(InputError) as artifact:
        verify.open_runner("a/step.tflite", providers=["CPUExecutionProvider"])
    assert str(artifact.value) == "--providers applies to onnxruntime; a/step.tflite runs on litert"
    with pytest.raises(InputError) as unknown:  # not run on ONNX Runtime under another name
        verify.open_runner(tmp_path / "missing.onnx", "tensorrt-fp8")
    assert str(unknown.value) == f"unknown runtime 'tensorrt-fp8'; choose one of {', '.join(verify.RUNTIMES)}"


def _graph_file(tmp_path) -> tuple[str, str]:
    import hashlib

    path = tmp_path / "g.onnx"
    path.write_bytes(b"stands for a graph: only its bytes' sha256 is read")
    return str(path), hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("quantization, profile", [(None, "fp32"), ({"mode": "int8", "budget": {"mpjpe_pct": 2.0}},
                                                                       "int8")])
def test_verify_graph_writes_the_report(tmp_path, monkeypatch, quantization, profile) -> None:
    """verify_graph on a fake runner and an in-memory golden: what it opens, the profile and
    budget it holds the graph to, and every field of the report it writes."""
    import dataclasses
    import json

    import numpy as np
    from _golden_fakes import STEPS, FakeRunner, make_golden

    runner = FakeRunner(np.full(STEPS, 1e-3), np.zeros(STEPS))
    runner.meta = dataclasses.replace(runner.meta, quantization=quantization)
    opened = []
    monkeypatch.setattr(verify, "open_runner", lambda model, runtime, threads=None, providers=None: (
        opened.append((model, runtime, threads, providers)) or runner))
    model, digest = _graph_file(tmp_path)
    golden = make_golden()
    result, report = verify.verify_graph(model, golden, tmp_path / "out", threads=2, header={"command": "test"})
    assert opened == [(model, "onnxruntime", 2, None)]
    assert result.profile == PROFILES[profile] and report["profile"] == PROFILES[profile].to_dict()
    assert result.budget is None or result.budget.budget == verify.resolve_budget(quantization)
    assert report["command"] == "test"
    assert report["model"] == {"path": model, "sha256": digest, "variant": "fake", "quantization": quantization}
    assert report["golden"] == {"path": "None", "source": {"variant": "fake"}, "steps": STEPS, "window_ms": None}
    assert (report["runtime"], report["providers"]) == ("onnxruntime", [])
    assert report["isa"] == verify.isa_comparison(quantization)
    assert report["budget_runtimes"] == verify.runtime_comparison(quantization, "onnxruntime")
    assert {k: report[k] for k in result.to_dict()} == result.to_dict() and "kernel_trace" not in report
    written = json.loads((tmp_path / "out" / "check.json").read_text())
    assert written == json.loads(json.dumps(report))
    import importlib.util

    plotted = importlib.util.find_spec("matplotlib") is not None
    assert report["plot"] == ("check.png" if plotted else None)
    assert (tmp_path / "out" / "check.png").is_file() == plotted
    _, unwritten = verify.verify_graph(model, golden, None)
    assert "plot" not in unwritten


def test_verify_graph_holds_a_given_budget_and_profile(tmp_path, monkeypatch) -> None:
    import dataclasses

    import numpy as np
    from _golden_fakes import STEPS, FakeRunner, make_golden

    runner = FakeRunner(np.zeros(STEPS), np.zeros(STEPS))
    runner.meta = dataclasses.replace(runner.meta, quantization={"mode": "int8"})
    monkeypatch.setattr(verify, "open_runner", lambda *args, **kwargs: runner)
    model, _ = _graph_file(tmp_path)
    result, report = verify.verify_graph(model, make_golden(), budget_pct=3.0, profile="int8", runtime="openvino",
                                         providers=None)
    assert result.budget.budget == TaskBudget(mpjpe_pct=3.0, pa_mpjpe_pct=3.0)
    assert report["runtime"] == "openvino" and report["budget_runtimes"]["runtime"] == "openvino"
