"""`--exclude auto` at its edges (issue 25, part 6), with injected evaluators and timers:
an error exactly at the budget is within it at every place a search compares them, and the
latency-aware choice is made against the user's budget, not the mode's default."""
from __future__ import annotations

import logging
from pathlib import Path

import pytest

from e3dpsm.quantize import api
from e3dpsm.quantize.api import DEFAULT_BUDGET_PCT, QuantizeOptions
from e3dpsm.quantize.exclusions import NodeRanking, SearchResult, greedy_exclusions, ranked_prefix_exclusions
from e3dpsm.quantize.graph_groups import NodeGroup

BUDGET = 1.0  # exactly representable, and every injected error below is too
NODES = [f"n{i}" for i in range(8)]


# -- within budget is inclusive ------------------------------------------------------------
@pytest.mark.parametrize("error, within", [(1.0, True), (1.0 + 2**-40, False), (0.5, True)])
def test_search_result_exactly_at_budget_is_within(error, within):
    result = SearchResult([], ["r"], error, BUDGET)
    assert result.within_budget is within and result.to_dict()["within_budget"] is within


def test_greedy_stops_at_a_base_error_exactly_at_budget_and_does_not_warn(caplog):
    calls = []

    def evaluate(excluded, label):
        calls.append(label)
        return BUDGET

    with caplog.at_level(logging.WARNING, logger="e3dpsm.quantize.exclusions"):
        result = greedy_exclusions(["r"], [NodeGroup("a", "module", ("a1",))], BUDGET, evaluate)
    assert calls == ["base"] and result.chosen == [] and result.within_budget
    assert not [r for r in caplog.records if "above" in r.getMessage()]


def test_greedy_takes_a_group_exactly_at_budget_and_stops():
    errors = {"base": 2.0, "a": 1.0, "b": 1.5}
    result = greedy_exclusions(["r"], [NodeGroup("a", "module", ("a1",)), NodeGroup("b", "module", ("b1",))],
                               BUDGET, lambda excluded, label: errors[label], max_rounds=3)
    assert result.chosen == ["a"] and result.error_pct == 1.0 and result.within_budget
    assert [t["round"] for t in result.trials] == [0, 1, 1]  # no second round


def _ranked(errors: dict[int, float]):
    """The ranked-prefix search over 8 nodes with error `errors[k]` for the top-k in float."""
    probed = []

    def evaluate(excluded, label):
        k = len(excluded) - 1  # beyond the one recurrent node
        probed.append(k)
        return errors[k]

    ranking = NodeRanking([{"node": n, "error_pct": 1.0} for n in NODES], frames=4)
    return ranked_prefix_exclusions(["r"], ranking, BUDGET, evaluate), probed


def test_ranked_doubling_stops_at_an_error_exactly_at_budget(caplog):
    # k = 1 over, k = 2 exactly at the budget: the answer, without probing 4 (or bisecting)
    errors = {0: 2.0, 1: 1.5, 2: 1.0, 3: 0.75, 4: 0.5, 8: 0.0}
    with caplog.at_level(logging.WARNING, logger="e3dpsm.quantize.exclusions"):
        result, probed = _ranked(errors)
    assert probed == [0, 1, 2]
    assert result.chosen == ["top2"] and result.excluded_nodes == ["r", "n0", "n1"]
    assert result.error_pct == 1.0 and result.within_budget
    assert not [r for r in caplog.records if "above" in r.getMessage()]


def test_ranked_bisection_takes_an_error_exactly_at_budget():
    # doubling: 1, 2 over, 4 within; bisection probes 3, exactly at the budget: the answer
    errors = {0: 2.0, 1: 1.75, 2: 1.5, 3: 1.0, 4: 0.5}
    result, probed = _ranked(errors)
    assert probed == [0, 1, 2, 4, 3]
    assert result.chosen == ["top3"] and result.error_pct == 1.0 and result.within_budget


def test_ranked_base_exactly_at_budget_needs_no_float_node():
    result, probed = _ranked({0: 1.0})
    assert probed == [0] and result.chosen == [] and result.within_budget


# -- the latency-aware choice reads the user's budget ---------------------------------------
# Keeping a in float removes 1.375 points of error, b 1.125, c 0.25 (base 2.0): a -> 0.625, b -> 0.875,
# c -> 1.75 (all exact in binary).
COST = {"a1": 1.375, "b1": 1.125, "c1": 0.25}
GROUPS = [NodeGroup("a", "module", ("a1",)), NodeGroup("b", "module", ("b1",)), NodeGroup("c", "op_type", ("c1",))]
P50_MS = {"base": 5.0, "r1:a": 30.0, "r1:b": 20.0, "r1:c": 10.0, "fp32": 40.0}  # b is faster than a


class _ComparingTimer:
    """A step timer with SideBySideTimer's `compare`: p50s from P50_MS, and a longer timing
    whose interval of the first graph's speed-up over the second is fixed at `low`-`high`."""

    def __init__(self, low: float, high: float) -> None:
        self.low, self.high, self.compared = low, high, []

    def __call__(self, graphs):
        return {label: P50_MS[label] for label in graphs}

    def compare(self, graph, reference, steps):
        self.compared.append((Path(graph).name, Path(reference).name, steps))
        mid = (self.low + self.high) / 2
        return {"speedup_vs_fp32": mid, "timer": {"steps": steps},
                "interval": {"speedup": mid, "low": self.low, "high": self.high, "coverage": 0.8, "rounds": 7}}


@pytest.mark.parametrize("low, chosen", [(1.05, ["b"]), (0.95, ["a"])])
def test_the_latency_pick_is_timed_again_beside_the_searchs_own_over_the_artifacts_steps(monkeypatch, tmp_path,
                                                                                       low, chosen):
    """b timed faster in the candidates' timing; the search's own choice is a (more accurate).
    quantize times b beside a over --artifact-timing-steps and ships b only when surely faster."""
    timer = _ComparingTimer(low, 1.3)
    final, latency, _ = _search_with(monkeypatch, tmp_path, "int8", 1.0, timer=timer, artifact_timing_steps=77)
    assert timer.compared == [("b.onnx", "a.onnx", 77)]  # the evaluator names graphs by group
    assert final.chosen == chosen and latency.confirmation["kept"] == (chosen == ["b"])


def _search_with(monkeypatch, tmp_path, mode: str, budget_pct: float | None, objective: str = "latency",
                 search_margin: float | None = 0.0, timer=None, **option_overrides):
    """api._latency_search with the held-out evaluation and the step timer injected."""
    def fake_evaluator(meta, holdout, options, work, build, built=None):
        def evaluate(excluded, label):
            built.append((list(excluded), tmp_path / f"{label}.onnx"))  # never opened: the timer is injected
            return 2.0 - sum(COST.get(n, 0.0) for n in excluded)
        return evaluate

    asked = []

    def fixed_timer(graphs):
        asked.append(set(graphs))
        return {label: P50_MS[label] for label in graphs}

    timer = timer or fixed_timer
    monkeypatch.setattr(api, "_evaluator", fake_evaluator)
    options = QuantizeOptions(mode=mode, budget_pct=budget_pct, search="groups", max_rounds=1, objective=objective,
                              search_margin=search_margin, **option_overrides)
    final, latency = api._latency_search(["r"], GROUPS, None, None, options, tmp_path, None,
                                         api._Timing(timer, tmp_path / "fp32.onnx"))
    return final, latency, asked


@pytest.mark.parametrize("mode, budget_pct, chosen, groups", [
    # int8 (default 1%): a (0.625) and b (0.875) are within 1%, b is faster. Under 0.7%
    # only a is within; under 0.5% none is, so the most accurate (a) is kept.
    ("int8", None, "r1:b", ["b"]),
    ("int8", 1.0, "r1:b", ["b"]),
    ("int8", 0.875, "r1:b", ["b"]),  # b exactly at the budget
    ("int8", 0.875 - 2**-40, "r1:a", ["a"]),
    ("int8", 0.7, "r1:a", ["a"]),
    ("int8", 0.5, "r1:a", ["a"]),
    # fp16 (default 0.1%): nothing is within it; a user's 1% makes b the fastest within
    ("fp16", None, "r1:a", ["a"]),
    ("fp16", 1.0, "r1:b", ["b"]),
])
def test_latency_choice_uses_the_given_budget_not_the_mode_default(monkeypatch, tmp_path, mode, budget_pct,
                                                                    chosen, groups):
    final, latency, asked = _search_with(monkeypatch, tmp_path, mode, budget_pct)
    budget = DEFAULT_BUDGET_PCT[mode] if budget_pct is None else budget_pct
    assert latency.chosen.label == chosen and final.chosen == groups
    assert latency.budget_pct == budget and final.budget_pct == budget
    assert final.within_budget is (final.error_pct <= budget)
    block = latency.to_dict()
    assert block["chosen"]["label"] == chosen
    assert [c["label"] for c in block["candidates"] if c["within_budget"]] == \
        [c.label for c in latency.candidates if c.error_pct <= budget]
    assert "fp32" in asked[0]


@pytest.mark.parametrize("budget_pct, margin, chosen, target", [
    (1.0, None, "r1:a", 0.75),     # int8's default margin (0.25): b (0.875) is over the 0.75 target
    (1.0, 0.25, "r1:a", 0.75),
    (1.0, 0.125, "r1:b", 0.875),   # b exactly at the target
    (1.0, 0.125 + 2**-40, "r1:a", 1.0 - 0.125 - 2**-40),
    (1.0, 0.0, "r1:b", 1.0),
])
def test_the_search_aims_below_the_budget_by_its_margin(monkeypatch, tmp_path, budget_pct, margin, chosen, target):
    """The search leaves a share of the budget for data it never saw: a candidate within the
    budget but over the target is not chosen; the graph still carries the whole budget."""
    final, latency, _ = _search_with(monkeypatch, tmp_path, "int8", budget_pct, search_margin=margin)
    assert latency.chosen.label == chosen
    assert final.budget_pct == pytest.approx(target) and latency.budget_pct == pytest.approx(target)
    options = QuantizeOptions(mode="int8", budget_pct=budget_pct, search_margin=margin)
    assert options.budget == budget_pct and options.search_target == pytest.approx(target)


@pytest.mark.parametrize("margin", [-0.1, 1.0, 1.5])
def test_search_margin_outside_zero_one_is_refused(margin):
    from e3dpsm.errors import ConfigError

    with pytest.raises(ConfigError, match="search-margin"):
        QuantizeOptions(mode="int8", search_margin=margin)


def test_fp16_keeps_its_whole_budget_by_default():
    assert QuantizeOptions(mode="fp16").search_target == QuantizeOptions(mode="fp16").budget == 0.1


def test_the_faster_group_is_chosen_only_when_within_the_users_budget(monkeypatch, tmp_path):
    """The case the mutation hides in: a user budget tighter than the mode's default,
    between the two candidates' errors (0.625 < 0.7 < 0.875 < 1.0): b is faster (P50_MS)
    but outside the budget, so it is neither worth timing nor chosen."""
    final, latency, asked = _search_with(monkeypatch, tmp_path, "int8", 0.7)
    assert P50_MS["r1:b"] < P50_MS["r1:a"]
    assert "r1:b" not in asked[0] and {"r1:a", "base", "fp32"} <= asked[0]
    assert latency.chosen.label == "r1:a" and final.error_pct == 0.625
    assert final.excluded_nodes == ["r", "a1"] and final.within_budget
