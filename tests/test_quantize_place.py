"""Pass 3's order (quantize/place.py) on injected evaluators: full integer first, the fewest
top-ranked nodes back to float, 16-bit activations first only on an NPU target, the inclusive
edge, FP16's greedy groups."""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import pytest

from e3dpsm.quantize.place import FULL_INTEGER, greedy_groups, place_precisions, smallest_prefix


@dataclass(frozen=True)
class Verdict:
    worst_share: float
    fidelity_pct: float = 0.0

    @property
    def within(self) -> bool:
        return self.worst_share <= 1.0


COST = {"a": 0.9, "b": 0.5, "c": 0.3, "d": 0.2, "e": 0.1}  # each node's share of the error at 8 bits


def evaluator(total: float = 2.0, calls: list | None = None, int16_factor: float | None = None):
    """A graph's worst share: `total` less the cost of each node returned to float (an int16
    node returns `1 - int16_factor` of its cost)."""
    def evaluate(floats, int16, label):
        if calls is not None:
            calls.append((tuple(floats), tuple(int16), label))
        saved = sum(COST[n] for n in floats) + sum(COST[n] * (1 - int16_factor) for n in int16)
        return Verdict(total - saved, fidelity_pct=total - saved)
    return evaluate


def test_full_integer_within_budget_ships_without_ranking():
    calls, ranked = [], []
    plan = place_precisions(list(COST), evaluator(0.95, calls), lambda n: ranked.append(n) or 0.0)
    assert plan.within and plan.float_nodes == () and plan.int16_nodes == ()
    assert calls == [((), (), FULL_INTEGER)] and ranked == []  # one trial, no ranking at all
    assert [t.label for t in plan.trials] == [FULL_INTEGER]


def test_the_fewest_top_ranked_nodes_return_to_float():
    calls = []
    # ranking: by solo error, highest first: a, b, c, d, e; 2.0 - a - b = 0.6 <= 1 but 2.0 - a = 1.1 > 1
    plan = place_precisions(list(COST), evaluator(2.0, calls), COST.__getitem__)
    assert plan.within and plan.float_nodes == ("a", "b") and plan.int16_nodes == ()
    assert [r[0] for r in plan.ranking] == ["a", "b", "c", "d", "e"]
    assert [c[0] for c in calls] == [(), ("a",), ("a", "b")]  # full integer, k = 1 over, k = 2 within
    assert not plan.trials[0].within and plan.trials[-1].within


def test_doubling_then_bisection_finds_the_smallest_prefix():
    probes = []
    fits = lambda k: probes.append(k) or k >= 11  # noqa: E731
    assert smallest_prefix(40, fits, max_probes=24) == 11
    assert probes == [1, 2, 4, 8, 16, 12, 10, 11]
    assert smallest_prefix(5, lambda k: False, max_probes=24) is None
    assert smallest_prefix(5, lambda k: k == 5, max_probes=24) == 5  # doubling stops at the end
    assert smallest_prefix(40, fits, max_probes=3) is None  # 1, 2, 4: out of probes


def test_a_prefix_exactly_at_the_budget_is_within():
    plan = place_precisions(list(COST), evaluator(1.9), COST.__getitem__)  # 1.9 - 0.9 = 1.0: on the edge
    assert plan.float_nodes == ("a",) and plan.trials[-1].worst_share == pytest.approx(1.0)
    over = place_precisions(list(COST), evaluator(1.9 + 1e-9), COST.__getitem__)
    assert over.float_nodes == ("a", "b")


def test_ties_in_the_ranking_break_by_name():
    plan = place_precisions(["z", "y", "x"], lambda f, i, label: Verdict(2.0 - len(f)), lambda n: 1.0)
    assert [r[0] for r in plan.ranking] == ["x", "y", "z"] and plan.float_nodes == ("x",)


def test_npu_targets_try_16_bit_activations_before_float():
    calls = []
    # at int16 a node keeps half its error: 1.9 - 0.5 (a + b + c) = 1.05 > 1, with d too 0.95 <= 1
    plan = place_precisions(list(COST), evaluator(1.9, calls, int16_factor=0.5), COST.__getitem__, int16=True)
    assert plan.within and plan.int16_nodes == ("a", "b", "c", "d") and plan.float_nodes == ()
    assert all(not c[0] for c in calls)  # never float while an int16 prefix met the budget


def test_npu_targets_fall_back_to_float_when_no_int16_prefix_fits():
    plan = place_precisions(list(COST), evaluator(3.0, int16_factor=0.5), COST.__getitem__, int16=True)
    # at int16 the best is 3.0 - 0.5 * 2.0 = 2.0 > 1: float prefixes then, 3.0 - 2.0 = 1.0 with all
    assert plan.int16_nodes == () and plan.float_nodes == ("a", "b", "c", "d", "e") and plan.within


def test_cpu_targets_never_place_16_bit_nodes():
    calls = []
    place_precisions(list(COST), evaluator(2.0, calls, int16_factor=0.0), COST.__getitem__)
    assert all(c[1] == () for c in calls)


def test_nothing_fits_returns_every_ranked_node_and_says_so(caplog):
    plan = place_precisions(list(COST), lambda f, i, label: Verdict(5.0), COST.__getitem__, max_trials=3)
    assert not plan.within and plan.float_nodes == tuple(COST) and "no prefix" in caplog.text
    report = plan.to_dict()
    assert report["within"] is False and len(report["trials"]) == 4  # full integer + 3 probes


def test_greedy_groups_add_the_most_helpful_group_until_within():
    groups = [("g1", ["a"]), ("g2", ["b", "c"]), ("g3", ["e"])]
    plan = greedy_groups(groups, evaluator(2.0))
    # round 1: g1 (2.0 - 0.9 = 1.1) beats g2 (1.2); round 2: g1 + g2 = 0.3 within
    assert plan.float_nodes == ("a", "b", "c") and plan.within
    assert [t.label for t in plan.trials] == ["all-fp16", "g1", "g2", "g3", "g2", "g3"]
    easy = greedy_groups(groups, evaluator(0.5))
    assert easy.float_nodes == () and len(easy.trials) == 1
    stuck = greedy_groups(groups, lambda f, i, label: Verdict(3.0))
    assert stuck.float_nodes == () and not stuck.within and len(stuck.trials) == 4  # no group helps: stop


# -- edges of the search and its report, by hand ----------------------------------------------
def test_no_compute_nodes_means_no_probe_beyond_full_integer():
    probes = []
    assert smallest_prefix(0, lambda k: probes.append(k) or True, max_probes=24) is None and probes == []
    plan = place_precisions([], evaluator(2.0), COST.__getitem__)
    assert not plan.within and plan.float_nodes == () and [t.label for t in plan.trials] == ["full-integer"]


def test_one_node_is_probed_and_an_unfitting_end_is_probed_once():
    assert smallest_prefix(1, lambda k: True, max_probes=24) == 1
    probes = []
    assert smallest_prefix(5, lambda k: probes.append(k) or False, max_probes=24) is None
    assert probes == [1, 2, 4, 5]  # doubling, then the whole list once: no probe repeats


def test_placement_report_by_hand():
    plan = place_precisions(list(COST), evaluator(2.0), COST.__getitem__)  # a, then a + b: hand-checked above
    assert plan.report_lines("test[:100]") == [
        "## Placement (search on test[:100])", "",
        "Full integer first, then the fewest top-ranked nodes out of 8 bits: 2 nodes return to float, "
        "0 take 16-bit activations.", "",
        "| trial | nodes to float | nodes at int16 | worst upper bound / limit | distance to fp32 % | within |",
        "|---|---:|---:|---:|---:|---|",
        "| full-integer | 0 | 0 | 2.000 | 2.000 | no |",
        "| top1-float | 1 | 0 | 1.100 | 1.100 | no |",
        "| top2-float | 2 | 0 | 0.600 | 0.600 | yes |", ""]
    assert plan.to_dict() == {
        "float_nodes": ["a", "b"], "int16_nodes": [], "within": True,
        "trials": [{"label": "full-integer", "float_nodes": 0, "int16_nodes": 0, "within": False,
                    "worst_share": 2.0, "distance_pct": 2.0},
                   {"label": "top1-float", "float_nodes": 1, "int16_nodes": 0, "within": False,
                    "worst_share": pytest.approx(1.1), "distance_pct": pytest.approx(1.1)},
                   {"label": "top2-float", "float_nodes": 2, "int16_nodes": 0, "within": True,
                    "worst_share": pytest.approx(0.6), "distance_pct": pytest.approx(0.6)}],
        "ranking": [{"node": n, "distance_pct": c} for n, c in COST.items()]}
    full = place_precisions(list(COST), evaluator(0.5), COST.__getitem__)
    assert "nodes out of 8 bits: the full-integer graph meets the budget there." in full.report_lines("x")[2]
    assert full.to_dict()["ranking"] == [] and full.to_dict()["trials"][0]["within"] is True
    npu = place_precisions(list(COST), evaluator(1.9, int16_factor=0.5), COST.__getitem__, int16=True)
    assert "0 nodes return to float, 4 take 16-bit activations." in npu.report_lines("x")[2]
    assert npu.to_dict()["int16_nodes"] == ["a", "b", "c", "d"]


def test_a_plan_cannot_be_changed_afterwards():
    plan = place_precisions(list(COST), evaluator(2.0), COST.__getitem__)
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.within = False
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.trials[0].within = True


def test_each_trial_is_evaluated_under_the_label_it_is_reported_by(caplog):
    calls = []
    caplog.set_level(logging.INFO, logger="e3dpsm.quantize.place")
    plan = place_precisions(list(COST), evaluator(2.0, calls), COST.__getitem__)
    assert [c[2] for c in calls] == [t.label for t in plan.trials] == ["full-integer", "top1-float", "top2-float"]
    assert caplog.records[-1].getMessage() == "2 ranked node(s) at float meet the budget"
    greedy_calls = []
    greedy = greedy_groups([("g1", ["a"]), ("g2", ["b", "c"])], evaluator(2.0, greedy_calls))
    assert [c[2] for c in greedy_calls] == [t.label for t in greedy.trials] == ["all-fp16", "g1", "g2", "g2"]


def test_running_out_of_probes_is_said_in_one_warning(caplog):
    place_precisions(list(COST), lambda f, i, label: Verdict(5.0), COST.__getitem__, max_trials=3)
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        "no prefix of the ranked nodes met the budget within 3 trials; every ranked node returns to float"]


def test_bisection_stops_at_its_probe_limit():
    probes = []
    fits = lambda k: probes.append(k) or k >= 11  # noqa: E731
    assert smallest_prefix(40, fits, max_probes=6) == 12  # the sixth probe fits: the best measured so far
    assert probes == [1, 2, 4, 8, 16, 12]
    probes.clear()
    assert smallest_prefix(40, fits, max_probes=7) == 12 and probes == [1, 2, 4, 8, 16, 12, 10]  # one more: 10 is over
