"""Pass 3's order (quantize/place.py) on injected evaluators: full integer first, the fewest
top-ranked nodes back to float, 16-bit activations first only on an NPU target, the inclusive
edge, FP16's greedy groups."""
from __future__ import annotations

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
