"""The precision search's edges on injected errors (quantize/precision.py): the budget is
inclusive at every stage, what each decision records (the report prints it), and the plan
unchanged where nothing fits. Written against survivors of `mutmut run --paths-to-mutate
quantize/precision.py` (2026-12-03); the main behaviour is in test_quantize_int16.py and
test_quantize_census.py."""
from __future__ import annotations

import pytest
from _precision_helpers import recurrent_evaluator, recurrent_plan

from e3dpsm.quantize.precision import (
    PrecisionChoice,
    PrecisionPlan,
    choose_precision,
    demote_to_int16,
    promote_to_int16w16,
    quantise_recurrent_compute,
    smallest_int16_plan,
)


def test_choice_reasons_say_what_met_the_budget_and_what_did_not() -> None:
    assert choose_precision("n", {"int8": 0.5}, 1.0).reason == "int8 meets the 1% budget (0.500%)"
    assert choose_precision("n", {"int8": 1.4, "int16w16": 1.2, "float": 0.8}, 1.0).reason == \
        "float meets the 1% budget (0.800%); int8 1.400%, int16w16 1.200% over it"
    none = choose_precision("n", {"int8": 3.0, "int16": 1.5}, 1.0)
    assert none.reason == "no precision meets the 1% budget (int8 3.000%, int16 1.500%); int16 is the most accurate"
    assert none.to_dict() == {"node": "n", "precision": "int16", "reason": none.reason,
                              "errors": {"int8": 3.0, "int16": 1.5}}


def test_at_equal_error_over_the_budget_the_higher_precision_is_kept() -> None:
    """No precision fits and two are equally accurate: the one with more bits (float if
    measured), as the docstring says; the lower one's equal figure is no evidence it is safe."""
    assert choose_precision("n", {"int8": 2.0, "int16": 1.5, "float": 1.5}, 1.0).precision == "float"
    assert choose_precision("n", {"int16": 1.5, "int16w16": 1.5}, 1.0).precision == "int16w16"


def test_unknown_or_missing_errors_are_refused() -> None:
    with pytest.raises(ValueError, match=r"unknown precision\(s\) \['int4'\]; choose from"):
        choose_precision("n", {"int8": 0.1, "int4": 0.1}, 1.0)
    with pytest.raises(ValueError, match="no measured error for node 'n'"):
        choose_precision("n", {}, 1.0)


def test_demotion_at_exactly_its_target_keeps_all_at_int16_and_records_each_choice() -> None:
    """The target is 0.4 + 0.5 x 0.6 = 0.7; all at int16 at exactly 0.7 fits in one trial."""
    plan = demote_to_int16(["a", "b"], 0.4, 1.0, lambda i, f, label: 0.7 if len(i) == 2 else 9.0)
    assert plan.int16 == ["a", "b"] and plan.float_nodes == [] and plan.error_pct == 0.7
    assert [(c.node, c.precision, c.errors) for c in plan.choices] == [
        ("a", "int16", {"int16": 0.7, "float": 0.4}), ("b", "int16", {"int16": 0.7, "float": 0.4})]
    assert plan.trials == [{"label": "int16_all", "int16_nodes": 2, "float_nodes": 0, "error_pct": 0.7}]


def test_demotion_records_every_trial_it_builds() -> None:
    plan = demote_to_int16(["a", "b"], 0.4, 1.0, lambda i, f, label: 0.4 + 0.25 * len(i))
    assert plan.trials == [{"label": "int16_all", "int16_nodes": 2, "float_nodes": 0, "error_pct": 0.9},
                           {"label": "int16_b", "int16_nodes": 1, "float_nodes": 1, "error_pct": 0.65},
                           {"label": "int16_a", "int16_nodes": 2, "float_nodes": 0, "error_pct": 0.9}]
    assert plan.to_dict() == {"target_pct": pytest.approx(0.7), "int16_nodes": ["b"], "int16w16_nodes": [],
                              "int8_recurrent_nodes": [], "float_nodes": ["a"], "error_pct": 0.65,
                              "choices": [c.to_dict() for c in plan.choices], "trials": plan.trials}


def test_a_candidate_at_exactly_the_budget_is_probed() -> None:
    index, probes = smallest_int16_plan([("top4", ["a"], 0.75)], 0.75, lambda nodes, label: 0.75)
    assert index == 0 and probes[0].fits and probes[0].target_pct == 0.75


def _float_plan(error: float = 0.5, target: float = 0.7) -> PrecisionPlan:
    choices = [PrecisionChoice(n, "float", "int16 over", {"int16": 2.0, "float": error}) for n in ("a", "b")]
    return PrecisionPlan(["x"], ["a", "b"], error, choices, [], target_pct=target)


def test_promotion_at_exactly_its_target_fits() -> None:
    together = promote_to_int16w16(_float_plan(), lambda i, w, f, label: 0.7)
    assert together.int16w16 == ["a", "b"] and [t["label"] for t in together.trials] == ["int16w16_all"]
    one = promote_to_int16w16(_float_plan(), lambda i, w, f, label: {1: 0.7}.get(len(w), 0.9))
    assert one.int16w16 == ["b"] and one.error_pct == 0.7  # b alone at exactly 0.7; then a 0.9


def test_promotion_that_fits_nowhere_leaves_the_plan_as_it_was_and_says_why() -> None:
    plan = promote_to_int16w16(_float_plan(), lambda i, w, f, label: 0.8 + 0.1 * len(w))
    assert plan.int16w16 == [] and plan.float_nodes == ["a", "b"] and plan.error_pct == 0.5
    assert plan.trials == [
        {"label": "int16w16_all", "int16_nodes": 1, "int16w16_nodes": 2, "float_nodes": 0, "error_pct": 1.0},
        {"label": "int16w16_b", "int16_nodes": 1, "int16w16_nodes": 1, "float_nodes": 1, "error_pct": 0.9},
        {"label": "int16w16_a", "int16_nodes": 1, "int16w16_nodes": 1, "float_nodes": 1, "error_pct": 0.9}]
    a = {c.node: c for c in plan.choices}["a"]
    assert a.precision == "float" and a.errors == {"int16": 2.0, "float": 0.5, "int16w16": 0.9}
    assert a.reason == "int16 over; int16w16 0.900% over the 0.7% target"


def test_recurrent_stage_budget_is_inclusive_and_records_its_trials() -> None:
    """All at int8 at exactly the target fits; the trial row names each precision's count."""
    cost8 = {"drive": 0.1, "read": 0.1}
    plan = quantise_recurrent_compute(recurrent_plan(), [["drive"], ["read"]], recurrent_evaluator(cost8, cost8, cost8=cost8))
    assert plan.int8 == ["drive", "read"] and plan.error_pct == pytest.approx(0.7)
    assert plan.trials[1:] == [{"label": "recurrent_int8_all", "int8_recurrent_nodes": 2, "int16_nodes": 1,
                                "int16w16_nodes": 1, "float_nodes": 1, "error_pct": pytest.approx(0.7)}]


def test_recurrent_units_at_exactly_the_target_fit_one_at_a_time_and_back_at_int8() -> None:
    # one at a time (all at once over): drive int8 0.5 + 0.2 = 0.7, exactly the target
    cost8, cost16 = {"drive": 0.2, "read": 0.5}, {"drive": 0.5, "read": 0.5}
    plan = quantise_recurrent_compute(recurrent_plan(), [["drive"], ["read"]], recurrent_evaluator(cost16, cost16, cost8=cost8))
    assert plan.int8 == ["drive"] and plan.float_nodes == ["f", "read"]
    # all at int16 fits (0.5 + 0.1 + 0.1); read back at int8: 0.5 + 0.1 + 0.1 = 0.7 exactly
    cost8, cost16 = {"drive": 0.2, "read": 0.1}, {"drive": 0.1, "read": 0.1}
    plan = quantise_recurrent_compute(recurrent_plan(), [["drive"], ["read"]], recurrent_evaluator(cost16, cost16, cost8=cost8))
    assert plan.int8 == ["read"] and plan.int16 == ["x", "drive"]


def test_recurrent_stage_with_nothing_that_fits_keeps_the_plans_error() -> None:
    plan = quantise_recurrent_compute(recurrent_plan(), [["read"]], recurrent_evaluator({"read": 0.3}, {"read": 0.3}, cost8={"read": 0.3}))
    assert plan.float_nodes == ["f", "read"] and plan.error_pct == 0.5


def test_recurrent_stage_at_a_plan_exactly_on_its_target_still_tries() -> None:
    """No slack left, but a precision that costs nothing still fits (<= target)."""
    plan = quantise_recurrent_compute(recurrent_plan(error=0.7), [["read"]], recurrent_evaluator({"read": 0.0}, {"read": 0.0},
                                                                                base=0.7, cost8={"read": 0.0}))
    assert plan.int8 == ["read"]
    over = recurrent_plan(error=0.71)
    assert quantise_recurrent_compute(over, [["read"]], recurrent_evaluator({"read": 0.0}, {"read": 0.0})) is over


def test_a_unit_reading_a_widened_tensor_starts_at_int16() -> None:
    """Not at int8 (its input is 16-bit already), but int16 is still tried before int16w16."""
    cost = {"read": 0.1}
    plan = quantise_recurrent_compute(recurrent_plan(), [["read"]], recurrent_evaluator(cost, cost, cost8={"read": 0.0}),
                                      no_int8={"read"})
    assert plan.int16 == ["x", "read"] and [t["label"] for t in plan.trials][1:] == ["recurrent_int16_all"]
