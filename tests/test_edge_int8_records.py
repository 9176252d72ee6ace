"""export/edge_int8.py's options and records, on hand-made budget checks: what convert.json and
the terminal say about an INT8 artifact (docs/edge.md#int8), and the splits the options refuse.
No conversion runs here (the converters end to end: test_edge_int8.py, test_litert_int8.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from e3dpsm.budget import BudgetCheck, MetricChange, TaskBudget
from e3dpsm.errors import ConfigError
from e3dpsm.export import edge_int8
from e3dpsm.quantize.holdout import HeldOut
from e3dpsm.quantize.place import Placement, Trial

BUDGET = TaskBudget()


def _check(mpjpe_upper: float = 0.4, jitter_upper: float = 3.0) -> BudgetCheck:
    metrics = (MetricChange("mpjpe", 100.0, 100.2, 0.2, 0.0, mpjpe_upper, 0.05, 1.0),
               MetricChange("pa_mpjpe", 50.0, 49.9, -0.2, -0.5, 0.1, 0.05, 1.0),
               MetricChange("jitter", 4.0, 4.1, 2.5, 1.0, jitter_upper, 0.3, 5.0))
    return BudgetCheck(metrics, frames=600, sequences=3, fidelity_mm=2.5, budget=BUDGET)


def _held(frames: int = 600) -> HeldOut:
    return HeldOut("prep/test", (np.zeros((frames, 2, 4, 4)),), (np.zeros((frames, 16, 3)),),
                   ({"pose": np.zeros((frames, 16, 3))},), 20.0)


def test_the_budget_record_says_what_convert_json_documents() -> None:
    record = edge_int8.budget_record(_check(), _held(), "litert")
    assert record == {
        "within": True, "runtime": "litert", "data": "prep/test", "frames": 600, "sequences": 3,
        "reference": "fp32 ONNX graph on ONNX Runtime", "distance_to_fp32_mm": 2.5,
        "distance_to_fp32_pct_of_mpjpe": pytest.approx(2.5),
        "metrics": {"mpjpe": {"fp32_mm": 100.0, "int8_mm": 100.2, "change_pct": 0.2, "upper_pct": 0.4,
                              "limit_pct": 1.0, "within": True, "precise": True},
                    "pa_mpjpe": {"fp32_mm": 50.0, "int8_mm": 49.9, "change_pct": -0.2, "upper_pct": 0.1,
                                 "limit_pct": 1.0, "within": True, "precise": True},
                    "jitter": {"fp32_mm": 4.0, "int8_mm": 4.1, "change_pct": 2.5, "upper_pct": 3.0,
                               "limit_pct": 5.0, "within": True, "precise": True}},
        "budget": BUDGET.to_dict()}
    over = edge_int8.budget_record(_check(mpjpe_upper=1.2), _held(), "executorch")
    assert over["within"] is False and over["metrics"]["mpjpe"]["within"] is False and over["runtime"] == "executorch"


def test_the_budget_line_names_each_metric_and_the_verdict() -> None:
    assert edge_int8.budget_line(_check()) == (
        "within budget on 600 held-out frames: mpjpe +0.20% (upper +0.40%, limit +1%), pa_mpjpe -0.20% (upper "
        "+0.10%, limit +1%), jitter +2.50% (upper +3.00%, limit +5%); 2.500 mm from the fp32 poses")
    assert edge_int8.budget_line(_check(jitter_upper=5.5)).startswith("OVER BUDGET on 600 held-out frames: ")


def test_the_search_record_lists_where_it_judged_and_every_trial() -> None:
    trials = (Trial("all-int8", 0, 0, False, 2.1, 4.0), Trial("model.decoder", 1, 0, True, 0.7, 1.5))
    placement = Placement(("model.decoder",), (), True, trials, (("model.decoder", 1.5),))
    options = edge_int8.EdgeInt8Options(search_frames=200)
    record = edge_int8.search_record(placement, _held(400), options, "PyTorch (PT2E)")
    assert record == {"split": "val", "frames": 400, "runtime": "PyTorch (PT2E)", "kept_float": ["model.decoder"],
                      **placement.to_dict()}


def test_the_search_keeps_the_block_whose_return_to_float_helps_most(monkeypatch) -> None:
    """search_float_groups: the full 8-bit artifact first; over budget, each block tried float
    once, and the one with the lowest worst share kept; trials judged through check_stepper
    on the search frames with the options' budget, each stepper from `trial(floats)`."""
    shares = {(): 2.0, ("a",): 1.5, ("b",): 0.8, ("c",): 1.2}
    seen = []

    def judged(stepper, search, budget):
        seen.append((stepper, search, budget))
        share = shares[stepper]
        return _check(mpjpe_upper=share)

    monkeypatch.setattr(edge_int8, "check_stepper", judged)
    options = edge_int8.EdgeInt8Options(search_rounds=2, budget=BUDGET)
    placement = edge_int8.search_float_groups(["a", "b", "c"], tuple, "SEARCH", options, "fake")
    assert placement.float_nodes == ("b",) and placement.within
    assert [t.label for t in placement.trials][0] == "all-int8"
    assert [s for s, _, _ in seen] == [(), ("a",), ("b",), ("c",)]
    assert all(search == "SEARCH" and budget is BUDGET for _, search, budget in seen)


@pytest.mark.parametrize("changes, message", [
    ({"split": "test"}, "the held-out split must differ from the calibration split ('test')"),
    ({"search_split": "train"}, "the search split ('train') must differ from the calibration and held-out splits: "
                                "the budget must hold on frames the search never saw"),
    ({"search_split": "test"}, "the search split ('test') must differ"),
    ({"holdout_frames": -1}, "--holdout-frames must be 0 or positive, got -1"),
    ({"search_frames": -5}, "--search-frames must be 0 or positive, got -5"),
    ({"search_rounds": -1}, "--search-rounds must be 0 or positive, got -1"),
    ({"narrow_trials": -2}, "--narrow-trials must be 0 or positive, got -2"),
])
def test_options_that_would_judge_on_seen_frames_or_count_backwards_are_refused(changes, message) -> None:
    with pytest.raises(ConfigError) as info:
        edge_int8.EdgeInt8Options(**changes)
    assert str(info.value).startswith(message)


def test_options_without_a_search_need_no_split_of_their_own_and_record_every_field() -> None:
    quiet = edge_int8.EdgeInt8Options(search_split="test", search_rounds=0, narrow_trials=0, search_frames=0)
    assert quiet.search_split == "test"
    options = edge_int8.EdgeInt8Options()
    assert (options.frames, options.split, options.holdout_split, options.holdout_frames, options.search_split,
            options.search_frames, options.search_rounds, options.narrow_trials, options.threads) == (
        200, "train", "test", 0, "val", 0, 4, None, None)
    assert options.to_dict() == {"frames": 200, "split": "train", "holdout_split": "test", "holdout_frames": 0,
                                 "search_split": "val", "search_frames": 0, "search_rounds": 4,
                                 "narrow_trials": None, "threads": None, "budget": TaskBudget().to_dict()}
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.frames = 1
