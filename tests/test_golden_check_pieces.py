"""e3dpsm/golden/check.py's verdicts on error series made by hand, each against an explicit loop
or a figure worked out in the docstring: growth over the rollout's quarters, the first failing
step of each rule, the reported steps, the records and lines `golden check` prints, and the
layout check's one line per mismatch. (Rollouts through real graphs: tests/test_golden.py.)"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from e3dpsm.errors import DataError
from e3dpsm.golden.check import (HOST_MEASURE, MIN_GROWTH_STEPS, REPORT_STEPS, GoldenCheck, TensorCheck,
                                 _state_error, check_layout)
from e3dpsm.golden.tolerances import PROFILES


def _state(errors, growth_limit=4.0, step_limit=math.inf) -> TensorCheck:
    return TensorCheck("s5", "state", "rel_rms", np.asarray(errors, float), step_limit, growth_limit=growth_limit)


def test_the_documented_constants() -> None:
    """docs/golden.md: errors reported at steps 1, 10, 100 and the last; growth judged from 20
    steps on (quarters of at least 5)."""
    assert REPORT_STEPS == (1, 10, 100) and MIN_GROWTH_STEPS == 20


@pytest.mark.parametrize("n", [20, 23, 41])
def test_growth_is_the_median_of_the_last_quarter_over_the_first(n) -> None:
    rng = np.random.default_rng(n)
    errors = rng.random(n) + 0.5
    quarter = n // 4
    early, late = sorted(errors[:quarter]), sorted(errors[n - quarter:])

    def median(values):  # by hand
        mid = len(values) // 2
        return values[mid] if len(values) % 2 else (values[mid - 1] + values[mid]) / 2

    assert _state(errors).growth == pytest.approx(median(late) / median(early))


def test_growth_needs_twenty_steps_and_a_first_quarter_above_zero() -> None:
    assert _state(np.ones(MIN_GROWTH_STEPS - 1)).growth is None
    assert _state(np.ones(MIN_GROWTH_STEPS)).growth == 1.0
    assert _state([0.0] * 5 + [7.0] * 10 + [0.0] * 5).growth == 1.0  # nothing early, nothing late
    assert _state([0.0] * 5 + [7.0] * 10 + [1e-6] * 5).growth == math.inf
    assert _state([1e-13] * 5 + [7.0] * 10 + [1e-13] * 5).growth == 1.0  # both below 1e-12: zero
    assert _state([1e-12] * 5 + [7.0] * 10 + [2e-12] * 5).growth == math.inf  # 1e-12 itself counts as zero
    assert _state([0.0] * 5 + [7.0] * 10 + [1e-12] * 5).growth == 1.0


@pytest.mark.parametrize("growth_limit, passed", [(None, True), (3.0, True), (2.999, False)])
def test_growth_passes_up_to_its_limit_inclusive(growth_limit, passed) -> None:
    check = _state([1.0] * 5 + [2.0] * 10 + [3.0] * 5, growth_limit=growth_limit)
    assert check.growth == 3.0 and check.growth_passed is passed and check.passed is passed


@pytest.mark.parametrize("early, late, floor, growth", [
    (0.001, 0.007, 0.0, 7.0),     # no floor: a tiny error's rise counts in full
    (0.001, 0.007, 0.05, 1.0),    # both under the floor: no growth
    (0.001, 0.25, 0.05, 5.0),     # started tiny, ended at a quarter of the state: judged against the floor
    (0.04, 0.3, 0.05, 6.0),       # the early median raised to the floor
    (0.1, 0.3, 0.05, 3.0),        # both over it: the plain ratio
])
def test_growth_raises_both_medians_to_the_floor(early, late, floor, growth) -> None:
    errors = [early] * 5 + [1.0] * 10 + [late] * 5
    check = TensorCheck("s5", "state", "rel_rms", np.asarray(errors), math.inf, growth_limit=4.0, growth_floor=floor)
    assert check.growth == pytest.approx(growth)
    assert check.passed is (growth <= 4.0)


def test_the_floor_sets_the_first_late_step_over_the_growth_bound() -> None:
    """Early median 0.001 raised to 0.05: the bound is 4 x 0.05 = 0.2, so the late step at
    0.19 is within and the one at 0.25 is the first over (without the floor: the first late step)."""
    errors = np.array([0.001] * 5 + [0.1] * 10 + [0.19, 0.25, 0.3, 0.3, 0.3])
    floored = TensorCheck("s5", "state", "rel_rms", errors, math.inf, growth_limit=4.0, growth_floor=0.05)
    assert floored.first_failing_step == 16
    assert TensorCheck("s5", "state", "rel_rms", errors, math.inf, growth_limit=4.0).first_failing_step == 15


def test_the_profiles_growth_floors() -> None:
    """A tenth of the state bound of each compressed profile; fp32 judges no growth."""
    assert PROFILES["int8"].growth_floor == PROFILES["bf16"].growth_floor == 0.05
    assert PROFILES["fp16"].growth_floor == 0.005 and PROFILES["fp32"].growth_floor is None


def _first_over_growth(errors, limit):
    """The first step of the last quarter over limit x the first quarter's median: a loop."""
    n = len(errors)
    bound = limit * float(np.median(errors[: n // 4]))
    for step in range(n - n // 4, n):
        if errors[step] > bound:
            return step
    return n - n // 4


def test_a_growth_failure_starts_at_the_first_late_step_over_the_bound() -> None:
    """n 24, quarters of 6: the first quarter's median is 2 (not the 1 of its first four), the
    bound 4.2 x 2 = 8.4; a late step exactly at the bound is not over it."""
    errors = np.array([1.0, 1.0, 1.0, 3.0, 3.0, 3.0] + [2.0] * 12 + [6.0, 8.4, 9.0, 10.0, 9.5, 12.0])
    check = _state(errors, growth_limit=4.2)
    assert not check.growth_passed and check.first_failing_step == _first_over_growth(errors, 4.2) == 20
    all_late = _state([1.0] * 5 + [2.0] * 10 + [9.0] * 5, growth_limit=4.0)
    assert all_late.first_failing_step == 15
    with_step = _state([1.0] * 5 + [2.0] * 10 + [9.0] * 5, growth_limit=4.0, step_limit=1.5)
    assert with_step.first_failing_step == 5  # the step limit fails earlier


def test_a_step_limit_fails_at_the_first_step_over_it_or_not_a_number() -> None:
    assert TensorCheck("pose", "output", "max_abs_mm", np.array([0.0, 0.01, 0.02, 0.0]), 0.01).first_failing_step == 2
    assert TensorCheck("pose", "output", "max_abs_mm", np.array([0.0, np.nan, 0.0]), 0.01).first_failing_step == 1
    assert TensorCheck("pose", "output", "max_abs_mm", np.array([0.01, 0.01]), 0.01).passed


def _running_mean_failure(errors, limit):
    """The step from which the running mean stays above `limit` to the end: a loop."""
    since, total = 0, 0.0
    for step, value in enumerate(errors):
        total += value
        if total / (step + 1) <= limit:
            since = step + 1
    return since


@pytest.mark.parametrize("errors", [
    [0.5, 0.5, 3.0, 0.1, 2.0, 2.0],
    [2.0, 0.0, 0.0, 2.5, 3.0],
    [3.0, 3.0, 3.0],
])
def test_a_mean_budget_fails_from_where_the_running_mean_stays_above_it(errors) -> None:
    check = TensorCheck("pose", "output", HOST_MEASURE, np.array(errors), 10.0, mean_limit=1.0)
    assert not check.mean_passed and check.first_failing_step == _running_mean_failure(errors, 1.0)


def test_the_mean_and_its_budget_at_their_edges() -> None:
    assert TensorCheck("pose", "output", HOST_MEASURE, np.zeros(0), 1.0).mean == 0.0
    assert TensorCheck("pose", "output", HOST_MEASURE, np.array([1.0, 3.0]), 10.0, mean_limit=2.0).mean_passed
    assert not TensorCheck("pose", "output", HOST_MEASURE, np.array([1.0, np.inf]), math.inf,
                           mean_limit=1e9).mean_passed
    assert TensorCheck("pose", "output", HOST_MEASURE, np.array([5.0]), 10.0).mean_passed  # no mean limit


@pytest.mark.parametrize("n, marks", [(1, ["1"]), (5, ["1", "5"]), (10, ["1", "10"]), (150, ["1", "10", "100", "150"]),
                                      (100, ["1", "10", "100"])])
def test_errors_are_reported_at_steps_1_10_100_and_the_last(n, marks) -> None:
    errors = np.arange(1, n + 1) / 10
    assert _state(errors).at_steps() == {m: int(m) / 10 for m in marks}


def test_a_tensors_record_and_line() -> None:
    errors = np.array([1.0] * 5 + [2.0] * 10 + [9.0, 3.0, 3.0, 3.0, 3.0])
    check = TensorCheck("s5_stage4_re", "state", "rel_rms", errors, math.inf, growth_limit=4.0)
    assert check.to_dict() == {
        "name": "s5_stage4_re", "kind": "state", "measure": "rel_rms", "passed": True, "max": 9.0, "max_at_step": 15,
        "mean": pytest.approx(float(errors.mean())), "step_limit": math.inf, "mean_limit": None,
        "first_failing_step": None, "at_steps": {"1": 1.0, "10": 2.0, "20": 3.0}, "growth": 3.0, "growth_limit": 4.0,
        "growth_floor": 0.0}
    assert check.line() == ("state  s5_stage4_re           max 9.000e+00    (step limit inf) growth x3.00 (limit x4)  ok")
    host = TensorCheck("pose", "output", HOST_MEASURE, np.array([0.5, np.nan, 2.0]), 1.0, mean_limit=0.25)
    record = host.to_dict()
    assert record["max_at_step"] == 2 and record["first_failing_step"] == 0 and record["passed"] is False
    assert host.line() == ("output pose                   max       nan mm (step limit 1.00e+00) mean       nan mm "
                           "(limit 2.50e-01)  FAIL from step 0")
    assert TensorCheck("pose", "output", "max_abs_mm", np.array([np.nan]), 1.0).to_dict()["max_at_step"] == 0


def _budget(answer: str, frames: int = 200):
    metrics = (SimpleNamespace(name="mpjpe", change_pct=0.4, upper_pct=0.9, limit_pct=1.0),
               SimpleNamespace(name="jitter", change_pct=6.0, upper_pct=7.5, limit_pct=5.0))
    return SimpleNamespace(answer=answer, metrics=metrics, frames=frames, to_dict=lambda: {"answer": answer})


def _golden_check(tensors, budget=None, steps=200, seconds=0.5) -> GoldenCheck:
    return GoldenCheck(PROFILES["int8"], 1000.0, tensors, steps, seconds, budget, {"runtime": "onnxruntime"})


def test_a_line_with_both_a_mean_budget_and_a_growth_bound() -> None:
    check = TensorCheck("pose", "output", HOST_MEASURE, np.ones(20), 5.0, mean_limit=2.0, growth_limit=4.0)
    assert check.line() == ("output pose                   max 1.000e+00 mm (step limit 5.00e+00) mean 1.000e+00 mm "
                            "(limit 2.00e+00) growth x1.00 (limit x4)  ok")


def test_a_check_without_a_budget_or_host_rollout() -> None:
    check = GoldenCheck(PROFILES["fp32"], None, [_state(np.ones(20))], 20, 0.1)
    assert check.budget is None and check.host is None and check.passed
    assert check.to_dict()["budget"] is None and check.to_dict()["host_rollout"] is None


def test_the_worst_metric_is_the_one_furthest_over_its_own_limit() -> None:
    """MPJPE at 1.2 of its limit of 1% is worse than jitter at 5.5% of 5% (1.1 of its limit),
    though 5.5 is the larger figure."""
    metrics = (SimpleNamespace(name="mpjpe", change_pct=0.8, upper_pct=1.2, limit_pct=1.0),
               SimpleNamespace(name="jitter", change_pct=4.0, upper_pct=5.5, limit_pct=5.0))
    for answer, start in (("over", "FAILED: over its accuracy budget, mpjpe +0.80%"),
                          ("undecided", "PASSED: 200 steps within the int8 profile; budget undecided on 200 frames "
                                        "(mpjpe +0.80%")):
        budget = SimpleNamespace(answer=answer, metrics=metrics, frames=200)
        assert _golden_check([_state(np.ones(20))], budget).summary().startswith(start)


def test_a_check_passes_on_its_tensors_and_a_budget_not_surely_over() -> None:
    good = _state(np.ones(20))
    assert _golden_check([good]).passed and _golden_check([good], _budget("within")).passed
    assert _golden_check([good], _budget("undecided")).passed and not _golden_check([good], _budget("over")).passed
    assert not _golden_check([good, _state(np.ones(20), step_limit=0.5)]).passed
    host = TensorCheck("pose", "output", HOST_MEASURE, np.zeros(20), 1.0)
    assert _golden_check([good, host], _budget("over")).questions == {"within_budget": "over", "same_as_host": True}
    assert _golden_check([good]).questions == {"within_budget": None, "same_as_host": None}
    bad_host = TensorCheck("pose", "output", HOST_MEASURE, np.full(20, 2.0), 1.0)
    assert _golden_check([host, bad_host]).questions["same_as_host"] is False


def test_the_summary_names_the_first_failure_or_the_budget() -> None:
    assert _golden_check([_state(np.ones(20))]).summary() == "PASSED: 200 steps within the int8 profile"
    assert _golden_check([_state(np.ones(20))], _budget("undecided", 60)).summary() == (
        "PASSED: 200 steps within the int8 profile; budget undecided on 60 frames (jitter +6.00%, upper bound "
        "+7.50% over +5%): record a longer golden to decide")
    assert _golden_check([_state(np.ones(20))], _budget("over")).summary() == (
        "FAILED: over its accuracy budget, jitter +6.00% (upper bound +7.50%, limit +5%)")
    late = TensorCheck("late", "output", HOST_MEASURE, np.array([0.0, 0.0, 3.0, 0.0]), 1.0)
    early = TensorCheck("early", "state", "rel_rms", np.array([0.0, 2.0, 3.0, 0.0]), 1.0)
    tie = TensorCheck("tie", "state", "rel_rms", np.array([0.0, 5.0, 0.0, 0.0]), 1.0)
    check = _golden_check([late, early, tie])
    assert check.first_failure == {"step": 1, "tensor": "early", "kind": "state", "error": 2.0, "step_limit": 1.0,
                                   "mean_limit": None, "measure": "rel_rms"}
    assert check.summary() == "FAILED: first at step 1, state early (rel_rms 2.000e+00, step limit 1.00e+00)"
    assert _golden_check([_state(np.ones(20))]).first_failure is None


def test_a_checks_record() -> None:
    tensors = [_state(np.ones(20))]
    record = _golden_check(tensors, _budget("within"), steps=200, seconds=0.5).to_dict()
    assert record == {"passed": True, "profile": PROFILES["int8"].to_dict(), "steps": 200,
                      "questions": {"within_budget": "within", "same_as_host": None}, "budget": {"answer": "within"},
                      "host_rollout": {"runtime": "onnxruntime"}, "scale_mm": 1000.0, "first_failure": None,
                      "seconds": 0.5, "ms_per_step": 2.5, "tensors": [tensors[0].to_dict()]}
    assert _golden_check(tensors, steps=0, seconds=0.0012345).to_dict()["ms_per_step"] == 1.234
    assert _golden_check(tensors, steps=3, seconds=0.0012345).to_dict()["seconds"] == 0.001


# ---- the layout check -------------------------------------------------------------------------------------
def _golden(**changes):
    manifest = {"source": {"variant": "tiny"}, "states": [{"name": "s5", "shape": [1, 2, 3]}]}
    fields = dict(manifest=manifest, frame_shape=(2, 8, 8), output_names=["pose", "pose_direct"])
    return SimpleNamespace(**{**fields, **changes})


def _meta(**changes):
    fields = dict(config={"variant": "tiny"}, frame_input={"shape": ["batch", 2, 8, 8]},
                  output_names=["pose_direct", "pose"], states=[SimpleNamespace(name="s5", shape=(2, 3))])
    return SimpleNamespace(**{**fields, **changes})


def test_a_graph_of_the_goldens_layout_passes_in_any_output_order() -> None:
    check_layout(_golden(), _meta())


@pytest.mark.parametrize("meta, message", [
    (_meta(config={"variant": "small"}), "the golden was recorded from variant 'tiny', the graph is 'small'"),
    (_meta(frame_input={"shape": [1, 2, 8, 9]}), "the graph takes frames [2, 8, 9], the golden holds [2, 8, 8]"),
    (_meta(output_names=["pose"]), "graph outputs ['pose'] differ from the golden's ['pose', 'pose_direct']"),
    (_meta(states=[SimpleNamespace(name="s5", shape=(2, 4))]),
     "the graph's states {'s5': [2, 4]} differ from the golden's {'s5': [2, 3]}"),
    (_meta(states=[SimpleNamespace(name="s6", shape=(2, 3))]),
     "the graph's states {'s6': [2, 3]} differ from the golden's {'s5': [2, 3]}"),
])
def test_each_layout_mismatch_is_one_line(meta, message) -> None:
    with pytest.raises(DataError) as info:
        check_layout(_golden(), meta)
    assert str(info.value) == message


# ---- a state's error --------------------------------------------------------------------------------------
class _Record:
    """What _state_error reads of a golden: a snapshot at one step, samples at every step."""

    def __init__(self, snapshot, index, samples, absmax):
        self._snapshot, self._index, self._samples, self._absmax = snapshot, index, samples, absmax

    def snapshot(self, _name):
        return self._snapshot

    def state_index(self, _name):
        return self._index

    def state_sample(self, _name):
        return self._samples

    def state_absmax(self, _name):
        return self._absmax


def test_a_states_error_by_hand() -> None:
    """fp32: max |diff| over the golden's magnitude (the whole state's at a sampled step, the
    snapshot's own at a snapshot step); compressed: ||diff|| / ||golden||."""
    ref = np.array([[3.0, -4.0, 0.0, 1.0]])
    record = _Record(ref[None], np.array([1, 3]), np.array([[-4.0, 1.0]]), np.array([8.0]))
    state = np.array([[3.0, -3.5, 0.0, 1.0]])[None]
    assert _state_error(record, "s", 0, state, 0, exact=True) == pytest.approx(0.5 / 4.0)
    assert _state_error(record, "s", 0, state, None, exact=True) == pytest.approx(0.5 / 8.0)  # absmax of the whole
    assert _state_error(record, "s", 0, state, 0, exact=False) == pytest.approx(0.5 / math.sqrt(26.0))
    assert _state_error(record, "s", 0, state, None, exact=False) == pytest.approx(0.5 / math.sqrt(17.0))
    zero = _Record(np.zeros((1, 1, 4)), np.array([0]), np.zeros((1, 1)), np.zeros(1))
    assert _state_error(zero, "s", 0, np.zeros((1, 1, 4)), 0, exact=False) == 0.0
    assert _state_error(zero, "s", 0, np.full((1, 1, 4), 1e-3), 0, exact=False) == math.inf
    assert _state_error(zero, "s", 0, np.full((1, 1, 4), 1e-3), 0, exact=True) == pytest.approx(1e-3 / 1e-12)
    nan = np.full((1, 1, 4), np.nan)
    assert _state_error(record, "s", 0, nan, 0, exact=True) == math.inf
    assert _state_error(record, "s", 0, nan, None, exact=True) == math.inf
    assert _state_error(record, "s", 0, nan, 0, exact=False) == math.inf
    empty = _Record(ref[None], np.zeros(0, int), np.zeros((1, 0)), np.array([8.0]))
    assert _state_error(empty, "s", 0, state, None, exact=True) == 0.0


def test_a_state_whose_golden_norm_is_exactly_tiny_counts_as_zero() -> None:
    """The relative RMS error divides by the golden's norm only above 1e-12; at 1e-12 the state
    is zero, and a difference of at most 1e-12 from it is none."""
    record = _Record(np.array([[[1e-12, 0.0, 0.0, 0.0]]]), np.array([0]), np.zeros((1, 1)), np.ones(1))
    assert _state_error(record, "s", 0, np.zeros((1, 1, 4)), 0, exact=False) == 0.0


def test_a_compressed_graph_needs_a_golden_with_ground_truth() -> None:
    from e3dpsm.golden.check import check_golden

    runner = SimpleNamespace(meta=_meta())
    with pytest.raises(DataError) as info:
        check_golden(runner, SimpleNamespace(**vars(_golden()), gt_mm=None), PROFILES["int8"])
    assert str(info.value) == ("the golden has no ground truth, so no accuracy budget for a compressed graph; "
                               "record it from prepared data or check with --profile fp32")
