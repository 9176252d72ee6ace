"""`golden check` limits at their edges (issue 25, part 6: mutations that passed every test).

A hand-made golden record (GoldenWriter, in memory) and a fake runner that returns the
golden outputs and states with errors chosen per step, so each limit of a tolerance
profile (the spike factor, the state RMS bound, the growth bound) and each step the
verdict names is checked on both sides of its edge against hand-computed numbers.
"""
from __future__ import annotations

import numpy as np
import pytest

from e3dpsm.golden.check import MIN_GROWTH_STEPS, TensorCheck, check_golden
from e3dpsm.golden.tolerances import PROFILES
from e3dpsm.golden.store import GoldenRecord, GoldenWriter
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.state import StateSpec, initial_states

J = 16
FRAME = (2, 4, 4)
STATE = "s"
STATE_SHAPE = (6,)
SCALE_MM = 100.0  # the golden's MPJPE scale: the int8 budget (1%) is 1 mm, its spike limit 10 mm
STEPS = 40  # quarters of 10 steps


def _golden_pose(step: int) -> np.ndarray:
    base = np.linspace(-800.0, 1200.0, 3 * J, dtype=np.float32).reshape(J, 3)
    return base + np.float32(step)


def _golden_state(step: int) -> np.ndarray:
    return (np.arange(1, 1 + STATE_SHAPE[0], dtype=np.float32) * (1.0 + 0.25 * step)).astype(np.float32)


def make_golden(steps: int = STEPS) -> GoldenRecord:
    writer = GoldenWriter(FRAME, ["pose"], {STATE: STATE_SHAPE}, steps)
    rng = np.random.default_rng(0)
    for step in range(steps):
        frame = (rng.random(FRAME) < 0.2).astype(np.float16)
        writer.add(frame, 20.0, None, {"pose": _golden_pose(step)[None]}, {STATE: _golden_state(step)[None]})
    manifest = {"steps": steps, "frame_shape": list(FRAME), "outputs": ["pose"],
                "states": [{"name": STATE, "shape": [-1, *STATE_SHAPE]}],
                "source": {"variant": "fake"}, "mpjpe_scale_mm": SCALE_MM}
    return GoldenRecord(manifest, writer.arrays())


class FakeRunner:
    """Returns the golden pose moved by `pose_mm[step]` mm (every joint along x: the mean
    joint distance is exactly that) and the golden state scaled by 1 + `state_rel[step]`
    (its relative RMS error is exactly that)."""

    def __init__(self, pose_mm, state_rel) -> None:
        self.pose_mm, self.state_rel = np.asarray(pose_mm, float), np.asarray(state_rel, float)
        self.step_index = 0
        self.meta = GraphMetadata(
            states=(StateSpec(STATE, STATE_SHAPE),),
            inputs={"frame": {"name": "lnes", "shape": ["batch", *FRAME]}, "window": {"name": "window_ms"}},
            outputs=[{"name": "pose"}], config={"variant": "fake"}, joints=[f"j{i}" for i in range(J)])

    def init_state(self, batch: int = 1):
        self.step_index = 0
        return initial_states(self.meta.states, batch)

    def step(self, lnes, state, window_ms):
        k = self.step_index
        self.step_index += 1
        pose = _golden_pose(k).astype(np.float64)
        pose[:, 0] += self.pose_mm[k]
        new_state = _golden_state(k).astype(np.float64) * (1.0 + self.state_rel[k])
        return {"pose": pose[None].astype(np.float32)}, {STATE: new_state[None].astype(np.float32)}


def _run(profile: str, pose_mm, state_rel, steps: int = STEPS):
    return check_golden(FakeRunner(pose_mm, state_rel), make_golden(steps), PROFILES[profile])


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


# -- 1. the spike limit: step_factor (10) budgets ------------------------------------------
@pytest.mark.parametrize("spike_budgets, passed", [(9.0, True), (11.0, False)])
def test_one_spike_over_ten_budgets_fails_under_the_mean_budget(spike_budgets, passed):
    budget_mm = PROFILES["int8"].budget_pct / 100.0 * SCALE_MM
    assert budget_mm == pytest.approx(1.0)
    pose = np.full(STEPS, 0.5 * budget_mm)
    pose[17] = spike_budgets * budget_mm
    assert pose.mean() < budget_mm  # the mean budget alone would pass: only the spike decides
    result = _run("int8", pose, np.zeros(STEPS))
    out = _tensor(result, "output")
    assert result.passed is passed
    assert out.first_failing_step == (None if passed else 17)
    assert out.step_limit == pytest.approx(10.0 * budget_mm)
    if not passed:
        assert result.first_failure["step"] == 17 and result.first_failure["tensor"] == "pose"


# -- 2. the first failing step of a mean budget ----------------------------------------------
def test_mean_budget_fails_from_the_step_after_the_running_mean_last_touches_it():
    # running mean: 2, 1, 2/3, 1/2, 1 (exactly the limit: within), 4/3, 11/7, 7/4 -> over from index 5
    errors = np.array([2.0, 0.0, 0.0, 0.0, 3.0, 3.0, 3.0, 3.0])
    check = TensorCheck("pose", "output", "mean_joint_distance_mm", errors, step_limit=10.0, mean_limit=1.0)
    running = np.cumsum(errors) / np.arange(1, 9)
    assert running[4] == 1.0 and np.all(running[5:] > 1.0)
    assert not check.mean_passed and check.first_failing_step == 5
    # never under the budget: it fails from the first step
    always = TensorCheck("pose", "output", "mean_joint_distance_mm", np.full(8, 2.0), 10.0, mean_limit=1.0)
    assert always.first_failing_step == 0
    # over only at the very last step: that step
    last = TensorCheck("pose", "output", "mean_joint_distance_mm", np.array([1.0] * 7 + [1.5]), 10.0, mean_limit=1.0)
    assert last.first_failing_step == 7


def test_mean_budget_first_failure_through_check_golden():
    """The same verdict end to end: a rollout whose running mean (1 mm budget) starts
    over, dips under it and rises again fails from the step after its last dip."""
    pose = np.full(STEPS, 2.0)
    pose[:6] = [4.0, 0.0, 0.0, 0.0, 0.0, 1.5]
    # running mean: 4, 2, 4/3, 1, 0.8, 5.5/6 = 0.917 (under), then 7.5/7 = 1.07, 9.5/8, ... -> 73.5/40
    running = np.cumsum(pose) / np.arange(1, STEPS + 1)
    assert running[4] == 0.8 and running[5] < 1.0 and np.all(running[6:] > 1.07)
    result = _run("int8", pose, np.zeros(STEPS))
    out = _tensor(result, "output")
    assert out.mean == pytest.approx((4.0 + 1.5 + 34 * 2.0) / STEPS, abs=1e-4)
    assert not out.mean_passed and out.first_failing_step == 6 and result.first_failure["step"] == 6


# -- 3. the int8 state bound: relative RMS 0.5 -----------------------------------------------
@pytest.mark.parametrize("profile, rel, passed", [
    ("int8", 0.4, True), ("int8", 0.6, False), ("fp16", 0.04, True), ("fp16", 0.06, False)])
def test_state_relative_rms_bound(profile, rel, passed):
    rel_per_step = np.full(STEPS, rel)  # constant: growth 1, only the per-step bound decides
    result = _run(profile, np.zeros(STEPS), rel_per_step)
    state = _tensor(result, "state")
    assert state.growth == pytest.approx(1.0)
    assert result.passed is passed and state.first_failing_step == (None if passed else 0)
    assert state.step_limit == {"int8": 0.5, "fp16": 0.05}[profile]


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
