"""`golden check` limits at their edges.

A hand-made golden record (GoldenWriter, in memory, with ground truth) and a fake runner that
returns the golden outputs and states with errors chosen per step, so each limit (the host
rollout's kernel-parity tolerance, the state RMS bound, the growth bound, the accuracy budget)
and each step the verdict names is checked on both sides of its edge against hand-computed
numbers, and each of a compressed graph's two questions fails on its own.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from e3dpsm.budget import TaskBudget
from e3dpsm.golden.check import HOST_MEASURE, MIN_GROWTH_STEPS, TensorCheck, check_golden
from e3dpsm.errors import DataError
from e3dpsm.golden.host import HostRollout, KernelParity, host_rollout_for
from e3dpsm.golden.tolerances import PROFILES
from _golden_fakes import (J, STATE, STATE_SHAPE, STEPS, FakeRunner, golden_pose,
                           golden_state, golden_writer, make_golden)
from e3dpsm.golden.store import GoldenRecord

def _run(profile: str, pose_mm, state_rel, steps: int = STEPS, **kwargs):
    return check_golden(FakeRunner(pose_mm, state_rel), make_golden(steps), PROFILES[profile], **kwargs)


def _host(shift_mm, steps: int = STEPS, kind: str = "vnni") -> HostRollout:
    """The host's rollout: the golden pose moved `shift_mm` (per step) along x."""
    poses = np.stack([golden_pose(k) for k in range(steps)]).astype(np.float64)
    poses[:, :, 0] += np.broadcast_to(np.asarray(shift_mm, float), (steps,))[:, None]
    return HostRollout({"graph": "g.onnx", "runtime": "onnxruntime", "isa": {"kind": kind}}, {"pose": poses})


def _tensor(result, kind: str) -> TensorCheck:
    return next(t for t in result.tensors if t.kind == kind)


def test_fake_record_measures_what_it_injects():
    """The harness itself: the measured errors are the injected ones."""
    pose = np.linspace(0.0, 0.9, STEPS)
    rel = np.linspace(0.1, 0.3, STEPS)  # growth under 3
    result = _run("int8", pose, rel)
    np.testing.assert_allclose(_tensor(result, "output").errors, pose, rtol=0, atol=2e-4)
    np.testing.assert_allclose(_tensor(result, "state").errors, rel, rtol=0, atol=1e-6)
    assert result.passed


# -- 1. a compressed graph's two questions, each failing on its own -------------------------
def test_over_budget_but_the_same_as_the_host_fails_on_the_budget_alone():
    # 30 mm along x beside 100 mm along y and 10 along z: MPJPE sqrt(100^2 + 10^2 + 30^2) against sqrt(100^2 + 10^2)
    result = _run("int8", np.full(STEPS, 30.0), np.zeros(STEPS), host=_host(30.0), isa_kind="vnni")
    assert result.questions == {"within_budget": "over", "same_as_host": True} and not result.passed
    mpjpe = result.budget.metric("mpjpe")
    assert mpjpe.change_pct == pytest.approx(100 * (np.sqrt(100.0**2 + 10**2 + 30**2) / np.hypot(100.0, 10.0) - 1),
                                             rel=1e-5)
    assert result.first_failure is None and "over its accuracy budget" in result.summary()


def test_within_budget_but_not_what_the_host_computed_fails_on_the_host_alone():
    result = _run("int8", np.zeros(STEPS), np.zeros(STEPS), host=_host(0.3), isa_kind="vnni")
    assert result.questions == {"within_budget": "within", "same_as_host": False} and not result.passed
    host = next(t for t in result.tensors if t.measure == HOST_MEASURE)
    assert host.mean == pytest.approx(0.3, abs=1e-4) and host.mean_limit == KernelParity().same_kind_mean_mm
    assert result.first_failure["tensor"] == "pose" and result.first_failure["measure"] == HOST_MEASURE


@pytest.mark.parametrize("kind, shift, passed", [("vnni", 0.009, True), ("vnni", 0.011, False),
                                                 ("avx2", 0.49, True), ("avx2", 0.51, False)])
def test_the_host_tolerance_knows_the_isa(kind, shift, passed):
    """The host recorded on a vnni host; this device is vnni: the same kernels, 0.01 mm; this
    device is another kind: the kernel-parity tolerance, 0.5 mm (mean)."""
    result = _run("int8", np.zeros(STEPS), np.zeros(STEPS), host=_host(shift), isa_kind="vnni" if kind == "vnni" else "arm")
    assert result.questions["same_as_host"] is passed and result.passed is passed


def test_one_step_over_the_host_step_limit_fails_from_that_step():
    shift = np.zeros(STEPS)
    shift[17] = 5.5  # mean 0.1375 mm, under 0.5; the step limit (5 mm) decides
    result = _run("int8", np.zeros(STEPS), np.zeros(STEPS), host=_host(shift), isa_kind="arm")
    host = next(t for t in result.tensors if t.measure == HOST_MEASURE)
    assert host.mean_passed and host.first_failing_step == 17 and not result.passed


def test_without_a_host_rollout_the_second_question_is_not_asked():
    result = _run("int8", np.zeros(STEPS), np.zeros(STEPS))
    assert result.questions == {"within_budget": "within", "same_as_host": None} and result.passed
    assert not any(t.measure == HOST_MEASURE for t in result.tensors)


def test_the_distance_to_fp32_is_reported_never_judged():
    result = _run("int8", np.full(STEPS, 3.0), np.zeros(STEPS), budget=TaskBudget(mpjpe_pct=50, pa_mpjpe_pct=50))
    fidelity = _tensor(result, "output")
    assert fidelity.mean == pytest.approx(3.0, abs=1e-4) and fidelity.step_limit == np.inf and result.passed


# -- 2. the first failing step of a mean limit ----------------------------------------------
def test_mean_limit_fails_from_the_step_after_the_running_mean_last_touches_it():
    errors = np.array([2.0, 0.0, 0.0, 2.0, 2.0])  # running mean: 2, 1, 0.67, 1, 1.2
    check = TensorCheck("pose", "output", HOST_MEASURE, errors, step_limit=10.0, mean_limit=1.0)
    assert not check.mean_passed and check.first_failing_step == 4
    # never under the limit: it fails from the first step
    always = TensorCheck("pose", "output", HOST_MEASURE, np.full(8, 2.0), 10.0, mean_limit=1.0)
    assert always.first_failing_step == 0
    # exactly at the limit is within
    last = TensorCheck("pose", "output", HOST_MEASURE, np.array([1.0] * 7 + [1.5]), 10.0, mean_limit=1.0)
    assert not last.mean_passed and last.first_failing_step == 7
    assert TensorCheck("pose", "output", HOST_MEASURE, np.ones(8), 10.0, mean_limit=1.0).passed


def test_mean_limit_first_failure_through_check_golden():
    """End to end: a host distance whose running mean (limit 1 mm) starts over, dips under it
    and rises again fails from the step after its last dip."""
    shift = np.full(STEPS, 2.0)
    shift[:6] = [4.0, 0.0, 0.0, 0.0, 0.0, 1.5]
    running = np.cumsum(shift) / np.arange(1, STEPS + 1)
    assert running[4] == 0.8 and running[5] < 1.0 and np.all(running[6:] > 1.07)
    parity = KernelParity(same_kind_mean_mm=1.0, same_kind_step_mm=10.0)
    result = _run("int8", np.zeros(STEPS), np.zeros(STEPS), host=_host(shift), isa_kind="vnni", parity=parity)
    host = next(t for t in result.tensors if t.measure == HOST_MEASURE)
    assert host.mean == pytest.approx((4.0 + 1.5 + 34 * 2.0) / STEPS, abs=1e-4)
    assert not host.mean_passed and host.first_failing_step == 6 and result.first_failure["step"] == 6


# -- 3. a compressed graph's state distance to fp32: reported, not judged -------------------
@pytest.mark.parametrize("profile, rel", [("int8", 0.4), ("int8", 0.6), ("fp16", 0.06), ("int8", 3.0)])
def test_a_compressed_graphs_state_distance_is_reported_not_judged(profile, rel):
    """INT8 S5 states sit about 0.5 relative RMS from fp32's: the distance is in the report,
    bounded growth is what is judged (constant here: growth 1)."""
    result = _run(profile, np.zeros(STEPS), np.full(STEPS, rel))
    state = _tensor(result, "state")
    assert state.growth == pytest.approx(1.0) and state.errors.max() == pytest.approx(rel, rel=1e-5)
    assert result.passed and state.first_failing_step is None


def test_the_fp32_profile_still_judges_every_states_step():
    result = _run("fp32", np.zeros(STEPS), np.where(np.arange(STEPS) >= 7, 2e-4, 0.0))
    assert not result.passed and _tensor(result, "state").first_failing_step == 7


# -- 4 / 11. the growth bound: late-quarter median / early-quarter median <= 4 ----------------
def _grown(early: float, late: float, n: int = STEPS) -> np.ndarray:
    """`early` over the first quarter, `late` over the last, a ramp between."""
    q = n // 4
    return np.concatenate([np.full(q, early), np.linspace(early, late, n - 2 * q), np.full(q, late)])


@pytest.mark.parametrize("late, passed", [(0.375, True), (0.5, True), (0.5 + 2**-10, False), (0.625, False)])
def test_growth_bound_at_its_edge(late, passed):
    """Early 0.125: growth 3, exactly 4 (within: the bound is inclusive), 4.03, 5."""
    errors = _grown(0.125, late)
    check = TensorCheck(STATE, "state", "rel_rms", errors, step_limit=1.0, growth_limit=4.0)
    assert check.growth == late / 0.125  # exact in binary
    assert check.growth_passed is passed and check.passed is passed
    # failing: from the first step of the last quarter over 4x the early median (hand-computed: step 30)
    assert check.first_failing_step == (None if passed else 30)


def test_growth_reads_the_last_quarter_not_the_first():
    errors = _grown(0.1, 0.5)  # 5x
    check = TensorCheck(STATE, "state", "rel_rms", errors, step_limit=1.0, growth_limit=4.0)
    assert check.growth == pytest.approx(5.0) and not check.passed
    assert check.first_failing_step >= STEPS - STEPS // 4
    # a shrinking error has growth < 1
    shrinking = TensorCheck(STATE, "state", "rel_rms", _grown(0.4, 0.1), step_limit=1.0, growth_limit=4.0)
    assert shrinking.growth == pytest.approx(0.25) and shrinking.passed
    # too short a rollout is not judged
    short = TensorCheck(STATE, "state", "rel_rms", _grown(0.1, 0.5, MIN_GROWTH_STEPS - 1), 1.0, growth_limit=4.0)
    assert short.growth is None and short.passed


@pytest.mark.parametrize("late, passed", [(0.3, True), (0.39, True), (0.41, False), (0.48, False)])
def test_int8_profile_growth_bound_end_to_end(late, passed):
    """Through check_golden with the int8 profile (growth limit 4, state bound 0.5): a
    state error rising from 0.1 to `late` (growth 3, 3.9, 4.1, 4.8) always within the
    per-step bound, so the growth bound alone decides."""
    rel = _grown(0.1, late)
    assert rel.max() <= PROFILES["int8"].state_rtol
    result = _run("int8", np.zeros(STEPS), rel)
    state = _tensor(result, "state")
    assert state.growth == pytest.approx(late / 0.1, rel=1e-5)
    assert result.passed is passed
    if not passed:
        assert state.first_failing_step == 30 and result.first_failure["step"] == 30
    assert state.growth_limit == 4.0


@pytest.mark.parametrize("entries, readable", [
    ([{"file": "host/step_int8-onnxruntime.npz", "sha256": "ab", "runtime": "onnxruntime"}], True),
    ([], True),
    ([{"file": "../step_int8-onnxruntime.npz", "sha256": "ab", "runtime": "onnxruntime"}], False),
    ([{"file": "host/../../etc/x.npz", "sha256": "ab", "runtime": "onnxruntime"}], False),
    ([{"file": "/tmp/x.npz", "sha256": "ab", "runtime": "onnxruntime"}], False),
    ([{"file": "host/x.pkl", "sha256": "ab", "runtime": "onnxruntime"}], False),
    ([{"file": "host/x.npz", "sha256": 3, "runtime": "onnxruntime"}], False),
    ({"file": "host/x.npz"}, False),
])
def test_host_rollouts_name_files_inside_the_golden_only(entries, readable, tmp_path):
    """golden check reads host/NAME.npz for a listed graph: a damaged or hand-edited manifest
    naming anything else is refused before any file is opened."""
    from e3dpsm.errors import DataError
    from e3dpsm.golden.store_checks import _check_host_rollouts

    if readable:
        _check_host_rollouts(entries, tmp_path / "golden.json")
    else:
        with pytest.raises(DataError, match="host_rollouts"):
            _check_host_rollouts(entries, tmp_path / "golden.json")


@pytest.mark.parametrize("lower, upper, answer, passed", [
    (-0.5, 4.9, "within", True), (-0.5, 5.0, "within", True),        # the upper end decides, inclusive
    (-0.5, 7.4, "undecided", True), (5.0, 9.0, "undecided", True),   # straddles (lower at the limit: not over)
    (5.01, 9.0, "over", False)])
def test_the_budget_question_is_within_over_or_undecided(lower, upper, answer, passed):
    """A golden too short to bound jitter inside +5% (a 200-frame pipeline golden: +2.97%,
    bound +7.43%) leaves the budget undecided: the device check passes and says so; a lower
    bound over the limit fails it."""
    from e3dpsm.budget import BudgetCheck, MetricChange
    from e3dpsm.golden.check import GoldenCheck

    metrics = (MetricChange("mpjpe", 100, 100, 0.0, -0.1, 0.1, 0.05, 1.0),
               MetricChange("pa_mpjpe", 80, 80, 0.0, -0.1, 0.1, 0.05, 1.0),
               MetricChange("jitter", 1.5, 1.54, (lower + upper) / 2, lower, upper, 2.5, 5.0))
    check = GoldenCheck(PROFILES["int8"], None, [], 200, 1.0, BudgetCheck(metrics, 200, 1, 2.4, TaskBudget()))
    assert check.budget.answer == answer and check.passed is passed
    assert check.questions["within_budget"] == answer
    assert ("budget undecided on 200 frames" in check.summary()) is (answer == "undecided")


# -- 5. the fp32 profile: parity at every step, no budget ------------------------------------
@pytest.mark.parametrize("pose_mm, state_rel, passed", [(0.009, 9e-5, True), (0.011, 9e-5, False),
                                                         (0.009, 1.1e-4, False)])
def test_fp32_profile_is_max_abs_per_step_and_state_relative_to_its_magnitude(pose_mm, state_rel, passed):
    """0.01 mm on every pose coordinate, 1e-4 of the state's largest magnitude (docs: parity)."""
    pose, rel = np.zeros(STEPS), np.zeros(STEPS)
    pose[12], rel[20] = pose_mm, state_rel  # step 20 is a snapshot step (1-2-5 series): whole-state path
    rel[7] = state_rel  # step 7 is not: the sampled elements against the recorded magnitude
    result = _run("fp32", pose, rel)
    output, state = _tensor(result, "output"), _tensor(result, "state")
    assert output.measure == "max_abs_mm" and state.measure == "rel_to_absmax"
    np.testing.assert_allclose(output.errors, pose, rtol=0, atol=2e-4)
    np.testing.assert_allclose(state.errors, rel, rtol=1e-2, atol=1e-9)
    assert result.budget is None and result.questions == {"within_budget": None, "same_as_host": None}
    assert result.passed is passed and state.growth_limit is None
    if not passed:
        assert result.first_failure["step"] == (12 if pose_mm > 0.01 else 7)


def test_the_verdict_lines_and_report_by_hand():
    pose = np.zeros(STEPS)
    pose[12] = 2.0**-5  # exact beside the float32 poses (about 1,000 mm: steps of 2^-14)
    failed = _run("fp32", pose, np.zeros(STEPS))
    assert failed.summary() == "FAILED: first at step 12, output pose (max_abs_mm 3.125e-02, step limit 1.00e-02)"
    assert failed.first_failure == {"step": 12, "tensor": "pose", "kind": "output", "error": 2.0**-5,
                                    "step_limit": 0.01, "mean_limit": None, "measure": "max_abs_mm"}
    output = _tensor(failed, "output")
    assert output.at_steps().keys() == {"1", "10", str(STEPS)}  # steps 1, 10, 100 and the last, where they exist
    assert output.at_steps()["1"] == 0.0
    row = output.to_dict()
    assert (row["passed"], row["max_at_step"], row["first_failing_step"]) == (False, 12, 12)
    assert row["max"] == 2.0**-5 and row["mean"] == pytest.approx(2.0**-5 / STEPS, rel=1e-12)
    assert output.line().startswith("output pose                   max 3.125e-02 mm (step limit 1.00e-02)")
    assert output.line().endswith("FAIL from step 12")
    report = failed.to_dict()
    assert (report["passed"], report["steps"], report["scale_mm"], report["budget"]) == (False, STEPS, 100.0, None)
    assert report["first_failure"]["step"] == 12 and len(report["tensors"]) == 2
    passed = _run("fp32", np.zeros(STEPS), np.zeros(STEPS))
    assert passed.summary() == f"PASSED: {STEPS} steps within the fp32 profile" and passed.first_failure is None
    assert _tensor(passed, "state").line().endswith("  ok")


def test_the_first_failure_is_the_earliest_step_then_the_first_tensor():
    pose, rel = np.zeros(STEPS), np.zeros(STEPS)
    pose[15], rel[15], rel[3] = 0.05, 0.5, 0.0
    both = _run("fp32", pose, rel)  # output and state both fail at 15: the output comes first
    assert both.first_failure["step"] == 15 and both.first_failure["kind"] == "output"
    rel[11] = 0.5  # the state now fails earlier
    assert _run("fp32", pose, rel).first_failure["kind"] == "state"


# -- the host rollout a check reads (golden/host.py) ------------------------------------------
def _golden_with_host(tmp_path, entries, arrays=None, steps: int = STEPS):
    golden = make_golden(steps)
    (tmp_path / "host").mkdir()
    for name, npz in (arrays or {}).items():
        np.savez(tmp_path / "host" / name, **npz)
    return GoldenRecord({**golden.manifest, "host_rollouts": entries}, golden.arrays, tmp_path)


def _entry(sha="abc", runtime="onnxruntime", kind="vnni", file="host/g-onnxruntime.npz"):
    return {"file": file, "graph": "g.onnx", "sha256": sha, "runtime": runtime, "isa": {"kind": kind}, "threads": 1}


def test_the_host_rollout_is_the_one_of_this_graph_and_runtime(tmp_path):
    poses = np.stack([golden_pose(k) for k in range(STEPS)])
    other = _entry(runtime="openvino", file="host/g-openvino.npz")
    golden = _golden_with_host(tmp_path, [other, _entry(), _entry(sha="def", file="host/h.npz")],
                               {"g-onnxruntime.npz": {"out.pose": poses}, "g-openvino.npz": {"out.pose": poses + 1},
                                "h.npz": {"out.pose": poses + 2}})
    found = host_rollout_for(golden, "abc", "onnxruntime")
    assert found.entry == _entry() and np.array_equal(found.outputs["pose"], poses)
    assert np.array_equal(host_rollout_for(golden, "abc", "openvino").outputs["pose"], poses + 1)
    assert host_rollout_for(golden, "abc", "tensorrt") is None and host_rollout_for(golden, "xyz", "onnxruntime") is None
    assert found.same_kind("vnni") and not found.same_kind("avx2")
    assert not HostRollout({"file": "x"}, {}).same_kind("")  # no ISA recorded: never the same kind
    in_memory = GoldenRecord(golden.manifest, golden.arrays)  # recorded, not loaded: no folder to read from
    assert host_rollout_for(in_memory, "abc", "onnxruntime") is None


class RecordingRunner(FakeRunner):
    """FakeRunner that keeps what it was given: the batch, each frame, window and state."""

    def __init__(self, shift_mm: float) -> None:
        super().__init__(np.full(STEPS, shift_mm), np.zeros(STEPS))
        self.batches, self.calls = [], []

    def init_state(self, batch: int = 1):
        self.batches.append(batch)
        return super().init_state(batch)

    def step(self, lnes, state, window_ms):
        self.calls.append((np.array(lnes), float(window_ms), np.array(state[STATE])))
        return super().step(lnes, state, window_ms)


def test_record_host_rollouts_keeps_each_graph_on_each_runtime_and_replaces_a_rerecord(tmp_path, monkeypatch):
    """golden/host.record_host_rollouts, with the runners faked: an ONNX graph once per runtime
    asked, a .tflite once on its own runtime (litert) whatever was asked; every golden frame and
    window stepped once from batch-1 initial states, each state carried into the next step; the
    outputs of every step kept (`out.<name>`, [steps, J, 3]) under `<stem>-<sha256[:12]>-<runtime>`;
    the manifest lists them with this host's ISA and the threads; recording one graph and
    runtime again replaces its entry and keeps the others."""
    import hashlib

    from e3dpsm.golden import verify
    from e3dpsm.golden.host import record_host_rollouts
    from e3dpsm.golden.store import load_golden
    from e3dpsm.utils.isa import detect_isa

    writer, manifest = golden_writer(STEPS)
    writer.write(tmp_path / "golden", {**manifest, "joints": [f"j{i}" for i in range(J)]})
    golden = load_golden(tmp_path / "golden")
    graph, artifact = tmp_path / "q.onnx", tmp_path / "q8.tflite"
    graph.write_bytes(b"onnx bytes")
    artifact.write_bytes(b"tflite bytes")
    shifts = {("q.onnx", "onnxruntime"): 1.0, ("q.onnx", "openvino"): 2.0, ("q8.tflite", "litert"): 3.0}
    runners = []

    def open_runner(model, runtime="onnxruntime", *, threads=None, providers=None):
        runners.append((Path(model).name, runtime, threads, RecordingRunner(shifts[(Path(model).name, runtime)])))
        return runners[-1][3]

    monkeypatch.setattr(verify, "open_runner", open_runner)
    entries = record_host_rollouts(tmp_path / "golden", [graph, artifact], ["onnxruntime", "openvino"], threads=3)
    assert [(name, runtime, threads) for name, runtime, threads, _ in runners] == [
        ("q.onnx", "onnxruntime", 3), ("q.onnx", "openvino", 3), ("q8.tflite", "litert", 3)]
    for *_, runner in runners:
        assert runner.batches == [1] and len(runner.calls) == STEPS
        for step, (frame, window, state) in enumerate(runner.calls):
            assert np.array_equal(frame, golden.frame(step)) and window == golden.window_ms(step)
            expected = np.zeros(STATE_SHAPE) if step == 0 else golden_state(step - 1)
            assert np.allclose(state[0], expected), step
    digest = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in (graph, artifact)}
    assert [e["file"] for e in entries] == [f"host/q-{digest['q.onnx'][:12]}-onnxruntime.npz",
                                            f"host/q-{digest['q.onnx'][:12]}-openvino.npz",
                                            f"host/q8-{digest['q8.tflite'][:12]}-litert.npz"]
    assert [(e["graph"], e["sha256"], e["runtime"], e["threads"]) for e in entries] == [
        ("q.onnx", digest["q.onnx"], "onnxruntime", 3), ("q.onnx", digest["q.onnx"], "openvino", 3),
        ("q8.tflite", digest["q8.tflite"], "litert", 3)]
    assert all(e["isa"] == detect_isa().to_dict() for e in entries)
    for entry, (*_, runner) in zip(entries, runners):
        with np.load(tmp_path / "golden" / entry["file"]) as saved:
            assert list(saved) == ["out.pose"] and saved["out.pose"].shape == (STEPS, J, 3)
            shift = runner.pose_mm[0]
            want = np.stack([golden_pose(k) + np.float32([shift, 0, 0]) for k in range(STEPS)])
            assert np.allclose(saved["out.pose"], want)
    reloaded = load_golden(tmp_path / "golden")
    assert reloaded.manifest["host_rollouts"] == entries and reloaded.manifest["steps"] == STEPS
    again = record_host_rollouts(tmp_path / "golden", [graph], ["openvino"], threads=1)
    listed = load_golden(tmp_path / "golden").manifest["host_rollouts"]
    assert listed == [entries[0], entries[2], *again] and again[0]["threads"] == 1


@pytest.mark.parametrize("arrays, message", [
    ({}, r"^\S+g-onnxruntime.npz: the host rollout the manifest lists is missing; record it again with golden "
         r"record --also$"),
    ({"g-onnxruntime.npz": {"out.other": np.zeros((STEPS, J, 3))}}, r"g-onnxruntime.npz: missing arrays \['out.pose'\]"),
    ({"g-onnxruntime.npz": {"out.pose": np.zeros((STEPS - 1, J, 3))}},
     rf"^\S+g-onnxruntime.npz does not hold the golden's {STEPS} steps; record it again$")])
def test_a_host_rollout_that_cannot_be_read_or_is_short_is_one_error(tmp_path, arrays, message):
    golden = _golden_with_host(tmp_path, [_entry()], arrays)
    with pytest.raises(DataError, match=message):
        host_rollout_for(golden, "abc", "onnxruntime")


@pytest.mark.parametrize("step_shift, passed", [(0.09, True), (0.11, False)])
def test_one_step_over_the_same_kind_step_limit_fails(step_shift, passed):
    """The host's own kind: 0.1 mm at any one step (the mean, 0.11 / 40, is far under 0.01 mm)."""
    shift = np.zeros(STEPS)
    shift[9] = step_shift
    result = _run("int8", np.zeros(STEPS), np.zeros(STEPS), host=_host(shift), isa_kind="vnni")
    host = next(t for t in result.tensors if t.measure == HOST_MEASURE)
    assert host.mean_passed and result.passed is passed and host.first_failing_step == (None if passed else 9)


def test_a_damaged_host_rollout_file_is_named_as_such(tmp_path):
    golden = _golden_with_host(tmp_path, [_entry()])
    (tmp_path / "host" / "g-onnxruntime.npz").write_bytes(b"PK\x03\x04 not a zip archive")
    with pytest.raises(DataError, match=r"g-onnxruntime.npz: cannot read the host rollout \(truncated or corrupted"):
        host_rollout_for(golden, "abc", "onnxruntime")


def test_the_tolerance_and_a_host_rollout_are_frozen():
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError):
        KernelParity().other_kind_mean_mm = 5.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        HostRollout({}, {}).entry = {"isa": {"kind": "vnni"}}


@pytest.mark.parametrize("mode, shift, passed", [("int8-weights", 0.009, True), ("int8-weights", 0.011, False),
                                                 ("int8", 0.011, True), (None, 0.49, True), ("int8", 0.51, False)])
def test_a_float_arithmetic_graph_gets_the_same_kind_tolerance_on_any_isa(mode, shift, passed):
    """Weight-only INT8 rounds no activation, so another ISA's kernels may differ from the
    host's by what fp32's do: 0.01 mm (mean) on another kind too, where INT8 gets 0.5."""
    from e3dpsm.golden.host import kernel_parity_for

    parity = kernel_parity_for({"mode": mode} if mode else None)
    result = _run("int8", np.zeros(STEPS), np.zeros(STEPS), host=_host(shift), isa_kind="arm", parity=parity)
    assert result.questions["same_as_host"] is passed
    assert parity.limits(True) == KernelParity().limits(True)  # the host's own kind: unchanged


@pytest.mark.parametrize("mode, passed", [("int8-weights", False), ("int8", True)])
def test_a_float_arithmetic_graph_gets_the_same_kind_step_limit_on_any_isa(mode, passed):
    """One step 0.2 mm off (the mean stays under 0.01 mm): over the 0.1 mm step limit a float
    graph keeps on another kind, within the 5 mm an INT8 one gets."""
    from e3dpsm.golden.host import kernel_parity_for

    shift = np.zeros(STEPS)
    shift[11] = 0.2
    assert shift.mean() < 0.01
    result = _run("int8", np.zeros(STEPS), np.zeros(STEPS), host=_host(shift), isa_kind="arm",
                  parity=kernel_parity_for({"mode": mode}))
    assert result.questions["same_as_host"] is passed
    assert passed or result.first_failure["step"] == 11


def test_check_golden_raises_the_state_medians_to_the_profiles_floor():
    """An S5 state 0.1% from fp32 early and 0.7% late (x7) is judged against the int8
    profile's floor, 0.05: no growth; the same errors with no floor fail from the last quarter."""
    from dataclasses import replace

    rel = np.concatenate([np.full(10, 0.001), np.full(20, 0.004), np.full(10, 0.007)])
    assert _tensor(_run("int8", np.zeros(STEPS), rel), "state").growth == pytest.approx(1.0)
    unfloored = check_golden(FakeRunner(np.zeros(STEPS), rel), make_golden(STEPS),
                             replace(PROFILES["int8"], growth_floor=0.0))
    state = _tensor(unfloored, "state")
    assert state.growth == pytest.approx(7.0, rel=1e-3) and state.first_failing_step == 30 and not unfloored.passed
