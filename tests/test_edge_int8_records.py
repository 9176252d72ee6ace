"""export/edge_int8.py's options and records, on hand-made budget checks: what convert.json and
the terminal say about an INT8 artifact (docs/edge.md#int8), and the splits the options refuse.
No conversion runs here (the converters end to end: test_edge_int8.py, test_litert_int8.py)."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from e3dpsm.budget import BudgetCheck, MetricChange, TaskBudget
from e3dpsm.errors import ConfigError, DataError
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


def test_the_trials_are_logged_and_recorded_as_the_cli_shows_them(monkeypatch, caplog) -> None:
    """Each search and narrowing trial is one INFO line (the CLI prints them as the conversion
    goes) and one record in convert.json; the Narrowing is a frozen record. The worst share is
    the largest upper end over its limit: jitter's 3.0 of 5 where MPJPE's is 0.5 of 1."""
    import logging

    monkeypatch.setattr(edge_int8, "check_stepper",
                        lambda floats, _s, _b: _check(mpjpe_upper=0.5 if {"g", "g/b"} & set(floats) else 1.5))
    options = edge_int8.EdgeInt8Options(search_rounds=1)
    with caplog.at_level(logging.INFO, logger="e3dpsm.export.edge_int8"):
        edge_int8.search_float_groups(["g"], tuple, None, options, "fake")
        narrowing = edge_int8.narrow_float_groups(["g"], {"g": ["g/a", "g/b"]}, list, None, options, "fake")
    assert [r.getMessage() for r in caplog.records] == [
        "INT8 search (fake): all-int8 (0 group(s) float): worst share 1.500",
        "INT8 search (fake): g (1 group(s) float): worst share 0.600, within",
        "INT8 narrowing (fake): g/a in 8 bits: worst share 0.600, within",
        "INT8 narrowing (fake): g/b in 8 bits: worst share 1.500"]
    assert narrowing.trials == [
        {"unit": "g/a", "group": "g", "within": True, "worst_share": 0.6, "distance_pct": pytest.approx(2.5)},
        {"unit": "g/b", "group": "g", "within": False, "worst_share": 1.5, "distance_pct": pytest.approx(2.5)}]
    assert narrowing.search_fields(("g",)) == {"kept_float": ["g/b"], "blocks_kept_float": ["g"],
                                               "narrowing": narrowing.trials, "narrowing_untried": []}
    with pytest.raises(dataclasses.FrozenInstanceError):
        narrowing.untried = []


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    """Four short synthetic sequences at the tiny's size (2 train, 1 val, 1 test)."""
    from _quantize_helpers import make_prepared

    return make_prepared(tmp_path_factory.mktemp("edge_int8_records"), seconds=0.4)


def test_the_reference_graph_and_the_held_out_and_search_frames(prepared, tmp_path) -> None:
    """open_data checks the folder against the model before anything converts; the fp32
    reference is the step graph in the work folder; the held-out and search sets are the test
    and val splits, named by folder and split, all frames or the first N of each sequence."""
    import shutil

    import e3dpsm
    from e3dpsm.data.prepared import PreparedData

    model = e3dpsm.create_model("tiny").eval()
    options = edge_int8.EdgeInt8Options(threads=1)
    data = edge_int8.open_data(prepared, model, options)
    reference = edge_int8.fp32_reference(model, tmp_path)
    assert reference == tmp_path / "fp32.onnx" and reference.is_file()
    held = edge_int8.held_out_set(reference, data, options)
    search = edge_int8.search_set(reference, data, edge_int8.EdgeInt8Options(threads=1, search_frames=7))
    assert (held.name, search.name) == ("prepared/test", "prepared/val")
    assert held.frames == sum(len(s.j3d_mm) for s in PreparedData.open(prepared).split("test"))
    assert search.frames == 7 * len(PreparedData.open(prepared).split("val"))
    no_val = tmp_path / "no_val"
    shutil.copytree(prepared, no_val)
    meta = json.loads((no_val / "meta.json").read_text())
    meta["sequences"] = [s for s in meta["sequences"] if s["split"] != "val"]
    (no_val / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DataError) as info:
        edge_int8.open_data(no_val, model, options)
    assert str(info.value).endswith(": the return-to-float search judges its trials there (--search-rounds 0 "
                                    "converts without it)")
    assert edge_int8.open_data(no_val, model, edge_int8.EdgeInt8Options(search_rounds=0)).root == no_val
    with pytest.raises((DataError, ConfigError)):
        edge_int8.open_data(prepared, e3dpsm.create_model("tiny", height=96, width=128), options)
