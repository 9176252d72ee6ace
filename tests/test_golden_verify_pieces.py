"""What `golden check` decides before it steps a graph (e3dpsm/golden/verify.py): the runtime an
artifact is checked on, the tolerance profile, the task budget, and the ISA and runtime notes the
report carries, each against hand-written expectations and every refusal compared whole."""
from __future__ import annotations

from pathlib import Path

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


class _Opened:
    def __init__(self, *args, **kwargs) -> None:
        self.args, self.kwargs = args, kwargs


def test_open_runner_opens_each_runtime_with_its_settings(monkeypatch) -> None:
    from e3dpsm.runtime import openvino_session, stepping

    monkeypatch.setattr(stepping, "open_stepper", _Opened)
    monkeypatch.setattr(openvino_session, "OpenVINOStepSession", _Opened)
    plain = verify.open_runner("g.onnx", threads=3)
    assert (plain.args, plain.kwargs) == (("g.onnx",), {"threads": 3})
    chosen = verify.open_runner("g.onnx", "onnxruntime", providers=["CPUExecutionProvider"])
    assert (chosen.args, chosen.kwargs) == (("g.onnx",), {"threads": None, "providers": ["CPUExecutionProvider"]})
    artifact = verify.open_runner("a/step.pte", threads=1)
    assert (artifact.args, artifact.kwargs) == (("a/step.pte",), {"threads": 1})
    for runtime, precision in (("openvino", "f32"), ("openvino-bf16", "bf16")):
        session = verify.open_runner("g.onnx", runtime, threads=2)
        assert (session.args, session.kwargs) == (("g.onnx",), {"threads": 2, "precision": precision})


class _Traced:
    """Records what verify_graph hands the host-rollout lookup, the kernel trace and the plot."""

    def __init__(self, monkeypatch, host_shift_mm: float | None) -> None:
        import numpy as np
        from _golden_fakes import STEPS, golden_pose

        from e3dpsm.golden import host as host_module
        from e3dpsm.golden.host import HostRollout

        self.lookups, self.traces, self.titles = [], [], []
        rollout = None
        if host_shift_mm is not None:
            poses = np.stack([golden_pose(k) for k in range(STEPS)]).astype(np.float64)
            poses[:, :, 0] += host_shift_mm
            rollout = HostRollout({"graph": "g.onnx", "runtime": "onnxruntime", "isa": {"kind": "vnni"}},
                                  {"pose": poses})

        def lookup(golden, digest, runtime):
            self.lookups.append((digest, runtime))
            return rollout

        monkeypatch.setattr(host_module, "host_rollout_for", lookup)
        monkeypatch.setattr(verify, "_kernel_trace", lambda folder, digest, threads: (
            self.traces.append((folder, digest, threads)) or {"trace": "here"}))
        monkeypatch.setattr(verify, "plot_check", lambda result, path, title: (
            self.titles.append(title), path.write_bytes(b"png")))


def _int8_runner(monkeypatch, pose_mm: float):
    import dataclasses

    import numpy as np
    from _golden_fakes import STEPS, FakeRunner

    runner = FakeRunner(np.full(STEPS, pose_mm), np.zeros(STEPS))
    runner.meta = dataclasses.replace(runner.meta, quantization={"mode": "int8"})
    monkeypatch.setattr(verify, "open_runner", lambda *args, **kwargs: runner)


@pytest.mark.parametrize("host_shift, folder, same, traced", [
    (0.0, True, True, False), (3.0, True, False, True), (3.0, False, False, False)])
def test_a_budget_profile_compares_with_the_hosts_rollout_and_traces_where_it_parts(
        tmp_path, monkeypatch, host_shift, folder, same, traced) -> None:
    from _golden_fakes import make_golden

    from e3dpsm.golden.store import GoldenRecord

    calls = _Traced(monkeypatch, host_shift)
    _int8_runner(monkeypatch, 0.0)
    model, digest = _graph_file(tmp_path)
    made = make_golden()
    golden = GoldenRecord({**made.manifest, "window_ms": 20.0}, made.arrays, tmp_path if folder else None)
    result, report = verify.verify_graph(model, golden, tmp_path / "a" / "b" / "out", threads=2)
    assert calls.lookups == [(digest, "onnxruntime")]
    assert result.questions["same_as_host"] is same and report["golden"]["window_ms"] == 20.0
    assert calls.traces == ([(tmp_path, digest, 2)] if traced else [])
    assert report.get("kernel_trace") == ({"trace": "here"} if traced else None)
    assert ("kernel_trace" in report) is traced
    verdict = "PASSED" if result.passed else "FAILED"
    assert calls.titles == [f"g.onnx on onnxruntime vs golden (int8): {verdict}"]
    verify.verify_graph(model, golden, tmp_path / "a" / "b" / "out")  # an existing folder is written again


def test_an_fp32_graph_never_looks_for_a_host_rollout(tmp_path, monkeypatch) -> None:
    from _golden_fakes import make_golden

    calls = _Traced(monkeypatch, 0.0)
    _int8_runner(monkeypatch, 0.0)
    progress = []
    check = verify.check_golden
    monkeypatch.setattr(verify, "check_golden", lambda *args, **kwargs: (
        progress.append(kwargs["progress"]) or check(*args, **kwargs)))
    model, _ = _graph_file(tmp_path)
    result, _ = verify.verify_graph(model, make_golden(), profile="fp32")
    assert calls.lookups == [] and result.questions["same_as_host"] is None
    verify.verify_graph(model, make_golden(), profile="fp32", progress=True)
    assert progress == [False, True]  # a progress bar only when asked


def test_the_kernel_trace_runs_where_the_golden_keeps_one(tmp_path, monkeypatch) -> None:
    from e3dpsm.golden import kernel_report

    found, ran = [], []
    monkeypatch.setattr(kernel_report, "find_trace", lambda golden, digest: (
        found.append((golden, digest)) or (tmp_path / "trace" if digest == "kept" else None)))
    monkeypatch.setattr(kernel_report, "run_device", lambda folder, threads, out: (
        ran.append((folder, threads, out.name, out.parent.is_dir())) or {"isolated": []}))
    assert verify._kernel_trace(tmp_path, "missing", None) is None and ran == []
    assert verify._kernel_trace(tmp_path, "kept", None) == {"isolated": []}
    assert verify._kernel_trace(tmp_path, "kept", 3) == {"isolated": []}
    assert found == [(tmp_path, "missing"), (tmp_path, "kept"), (tmp_path, "kept")]
    assert ran == [(tmp_path / "trace", 1, "trace.json", True), (tmp_path / "trace", 3, "trace.json", True)]


def test_a_golden_recorded_before_the_growth_floor_takes_todays_floor_and_keeps_its_own_numbers() -> None:
    recorded = {"name": "int8", "kind": "budget", "state_rtol": 0.5, "max_growth": 3.0}  # no growth_floor yet
    chosen = verify.resolve_profile("int8", None, {"tolerances": {"int8": recorded}})
    assert chosen.max_growth == 3.0 and chosen.growth_floor == PROFILES["int8"].growth_floor == 0.05


@pytest.mark.parametrize("name, key", [("g.onnx", "kernel_trace"), ("step.pte", "code_trace"),
                                       ("step.tflite", "code_trace")])
def test_where_a_machine_parts_is_traced_by_the_artifacts_own_kind(tmp_path, monkeypatch, name, key) -> None:
    """A QDQ graph's departure goes to the kernel trace, a .pte's and a .tflite's to their code
    trace (golden/artifact_trace.py), each with the checked file, its digest and the threads."""
    import hashlib

    from _golden_fakes import make_golden

    from e3dpsm.golden.store import GoldenRecord

    calls = _Traced(monkeypatch, 3.0)
    coded = []
    monkeypatch.setattr(verify, "_code_trace", lambda folder, model, digest, threads: (
        coded.append((folder, Path(model).name, digest, threads)) or {"trace": "codes"}))
    _int8_runner(monkeypatch, 0.0)
    model = tmp_path / name
    model.write_bytes(b"an artifact's bytes")
    digest = hashlib.sha256(model.read_bytes()).hexdigest()
    made = make_golden()
    golden = GoldenRecord({**made.manifest, "window_ms": 20.0}, made.arrays, tmp_path)
    result, report = verify.verify_graph(str(model), golden, threads=2)
    assert result.questions["same_as_host"] is False
    assert {k: report[k] for k in ("kernel_trace", "code_trace") if k in report} == {
        key: {"trace": "here"} if key == "kernel_trace" else {"trace": "codes"}}
    assert (calls.traces, coded) == (([(tmp_path, digest, 2)], []) if key == "kernel_trace" else
                                     ([], [(tmp_path, name, digest, 2)]))


def test_the_code_trace_reads_the_golden_with_one_thread_unless_told(tmp_path, monkeypatch) -> None:
    from e3dpsm.golden import artifact_trace

    ran = []
    monkeypatch.setattr(artifact_trace, "run_device", lambda *args: ran.append(args) or {"trace": "pte_taps"})
    assert verify._code_trace(tmp_path, "a/step.pte", "d", None) == {"trace": "pte_taps"}
    verify._code_trace(tmp_path, "a/step.pte", "d", 4)
    assert ran == [(tmp_path, "a/step.pte", "d", 1), (tmp_path, "a/step.pte", "d", 4)]
