"""Latency-aware `--exclude auto`: the fastest candidate within the budget, timings injected."""
from __future__ import annotations

import json

import pytest

from e3dpsm.errors import ConfigError
from e3dpsm.quantize import QuantizeOptions, quantize_graph
from e3dpsm.quantize.exclusions import greedy_exclusions
from e3dpsm.quantize.front import (
    Candidate, candidates_from_search, latency_aware_choice, pareto_front,
)
from e3dpsm.quantize.graph_groups import NodeGroup

# Synthetic search: the error each node kept in float removes (as in test_quantize.py).
COST = {"a1": 1.4, "b1": 1.1, "c1": 0.2}
GROUPS = [NodeGroup("a", "module", ("a1",)), NodeGroup("b", "module", ("b1",)), NodeGroup("c", "op_type", ("c1",))]


def _search(budget: float = 1.0):
    """Base error 2.0; keeping a -> 0.6, b -> 0.9 (both within a 1% budget), c -> 1.8."""
    built = []

    def evaluate(excluded, label):
        built.append((list(excluded), None))
        return 2.0 - sum(COST.get(n, 0.0) for n in excluded)

    result = greedy_exclusions(["r"], GROUPS, budget, evaluate, max_rounds=1)
    return result, candidates_from_search(result, built)


def _timer(ms: dict[str, float]):
    """An injected step timer: fixed p50 per label; records what it was asked to time."""
    asked: list[set[str]] = []

    def timer(graphs):
        asked.append(set(graphs))
        return {label: ms[label] for label in graphs if label in ms}

    timer.asked = asked
    return timer


def _with_paths(cands):
    for c in cands:
        c.path = f"/nowhere/{c.label}.onnx"  # the injected timer never opens them
    return cands


def test_latency_objective_picks_the_faster_of_two_candidates_within_budget():
    result, cands = _search()
    assert result.chosen == ["a"]  # the greedy (accuracy) choice: the lower error
    timer = _timer({"r1:a": 30.0, "r1:b": 20.0, "base": 10.0, "fp32": 40.0})
    fast = latency_aware_choice(result, _with_paths(cands), timer, "latency", 1.0, reference="/fp32.onnx")
    assert fast.chosen.label == "r1:b" and fast.chosen.groups == ["b"] and fast.chosen.p50_ms == 20.0
    assert fast.chosen.excluded_nodes == ["r", "b1"]
    assert "fp32" in timer.asked[0] and {"r1:a", "r1:b", "base"} <= timer.asked[0]
    report = fast.to_dict()
    assert report["chosen"]["label"] == "r1:b" and report["fp32_p50_ms"] == 40.0
    assert report["chosen"]["speedup_vs_fp32"] == pytest.approx(2.0)
    # the same timings under the accuracy objective: the more accurate one
    _, cands = _search()
    accurate = latency_aware_choice(result, _with_paths(cands), timer, "accuracy", 1.0)
    assert accurate.chosen.label == "r1:a" and accurate.chosen.error_pct == pytest.approx(0.6)
    # and with the timings swapped the latency objective agrees with it
    _, cands = _search()
    swapped = latency_aware_choice(result, _with_paths(cands), _timer({"r1:a": 20.0, "r1:b": 30.0}), "latency", 1.0)
    assert swapped.chosen.label == "r1:a"
    # timings within the tie tolerance (1.5% apart) do not buy accuracy away
    _, cands = _search()
    tie = latency_aware_choice(result, _with_paths(cands), _timer({"r1:a": 20.3, "r1:b": 20.0}), "latency", 1.0)
    assert tie.chosen.label == "r1:a"


def test_a_faster_candidate_outside_the_budget_is_never_chosen():
    result, cands = _search()
    # base (2.0%) and c (1.8%) are the fastest but above the 1% budget
    timer = _timer({"base": 1.0, "r1:c": 2.0, "r1:a": 30.0, "r1:b": 20.0})
    choice = latency_aware_choice(result, _with_paths(cands), timer, "latency", 1.0, max_timed=10)
    assert choice.chosen.label == "r1:b"
    assert all(c.error_pct <= 1.0 for c in [choice.chosen])
    # nothing within budget: the most accurate graph the search found, however slow
    tight, cands = _search(budget=0.1)
    timer = _timer({"base": 1.0, "r1:c": 2.0, "r1:a": 30.0, "r1:b": 20.0})
    stuck = latency_aware_choice(tight, _with_paths(cands), timer, "latency", 0.1, max_timed=10)
    assert stuck.chosen.label == "r1:a" and not stuck.to_dict()["chosen"]["within_budget"]


def test_timing_is_bounded_and_untimed_candidates_are_never_chosen():
    result, cands = _search()
    timer = _timer({"base": 1.0, "r1:c": 2.0, "r1:a": 30.0, "r1:b": 20.0})
    choice = latency_aware_choice(result, _with_paths(cands), timer, "latency", 1.0, max_timed=1)
    # only the greedy choice was timed (the budget of one timing), so it is the answer
    assert timer.asked == [{"r1:a"}] and choice.chosen.label == "r1:a"
    assert [c.label for c in choice.candidates if c.p50_ms is None] == ["base", "r1:b", "r1:c"]
    with pytest.raises(ConfigError, match="objective"):
        latency_aware_choice(result, cands, timer, "speed", 1.0)
    with pytest.raises(ConfigError, match="objective"):
        QuantizeOptions(objective="speed")


def _confirm(low: float, high: float):
    """An injected longer timing (SideBySideTimer.compare bound to its steps): a fixed
    interval of the speed-up of the first graph over the second; records what it compared."""
    asked: list[tuple[str, str]] = []

    def confirm(graph, reference):
        asked.append((str(graph), str(reference)))
        return {"speedup_vs_fp32": (low + high) / 2, "timer": {"steps": 200},
                "interval": {"speedup": (low + high) / 2, "low": low, "high": high, "coverage": 0.8, "rounds": 20}}

    confirm.asked = asked
    return confirm


@pytest.mark.parametrize("low, high, ships", [(1.02, 1.4, "r1:b"), (1.0, 1.4, "r1:a"), (0.7, 1.3, "r1:a")])
def test_a_latency_pick_ships_only_if_timed_surely_faster_than_the_searchs_own(low, high, ships):
    """The 30-step timing says r1:b (within budget) is the fastest; timed again beside the
    search's own choice r1:a it ships only where the interval's lower end is above 1 (1.0
    itself is not: the boundary case)."""
    result, cands = _search()
    confirm = _confirm(low, high)
    timer = _timer({"r1:a": 30.0, "r1:b": 20.0, "base": 10.0, "fp32": 40.0})
    search = latency_aware_choice(result, _with_paths(cands), timer, "latency", 1.0, reference="/fp32.onnx",
                                  confirm=confirm)
    assert search.chosen.label == ships
    assert confirm.asked == [("/nowhere/r1:b.onnx", "/nowhere/r1:a.onnx")]
    block = search.to_dict()["confirmation"]
    assert block["candidate"] == "r1:b" and block["against"] == "r1:a" and block["kept"] == (ships == "r1:b")
    assert block["interval"]["low"] == low and block["steps"] == 200


def test_nothing_is_confirmed_when_the_pick_is_the_searchs_own_or_the_objective_is_not_latency():
    result, cands = _search()
    confirm = _confirm(0.5, 0.6)
    own_fastest = latency_aware_choice(result, _with_paths(cands), _timer({"r1:a": 20.0, "r1:b": 30.0}),
                                       "latency", 1.0, confirm=confirm)
    assert own_fastest.chosen.label == "r1:a" and own_fastest.confirmation is None
    _, cands = _search()
    accurate = latency_aware_choice(result, _with_paths(cands), _timer({"r1:a": 30.0, "r1:b": 20.0}),
                                    "accuracy", 1.0, confirm=confirm)
    assert accurate.chosen.label == "r1:a" and accurate.confirmation is None
    assert confirm.asked == []


def test_report_says_whether_the_latency_pick_was_confirmed():
    from e3dpsm.quantize.front_report import confirmation_lines, speed_verdict

    result, cands = _search()
    timer = _timer({"r1:a": 30.0, "r1:b": 20.0, "base": 10.0, "fp32": 25.0})
    search = latency_aware_choice(result, _with_paths(cands), timer, "latency", 1.0, reference="/fp32.onnx",
                                  confirm=_confirm(0.9, 1.2))
    block = search.to_dict()
    assert confirmation_lines(block["confirmation"])[0] == (
        "The fastest candidate within budget, `r1:b`, timed again beside the search's own choice `r1:a`: "
        "1.05x (200 steps, 80% interval 0.90-1.20x), not surely faster, so the search's own choice ships.")
    # the verdict (the artifact no faster than fp32) does not tell the reader the latency
    # objective picks the candidate that timed 1.25x in 30 steps: it was not confirmed
    report = {"mode": "int8", "search": block, "machine": {"isa": {"kind": "vnni", "flags": ["avx512_vnni"]}},
              "artifact_timing": {"p50_ms": 30.0, "fp32_p50_ms": 25.0}}
    verdict = speed_verdict(report)
    assert "--objective latency picks it" not in verdict
    assert "timed 1.25x in the search's short timing, and not surely faster" in verdict


def test_report_shows_the_front_as_a_table_and_a_plot(tmp_path):
    from e3dpsm.quantize.front_report import markdown_report, write_search_outputs

    result, cands = _search()
    timer = _timer({"base": 10.0, "r1:a": 30.0, "r1:b": 20.0, "fp32": 40.0})
    search = latency_aware_choice(result, _with_paths(cands), timer, "latency", 1.0, reference="/fp32.onnx",
                                  timer_info={"steps": 30, "warmup": 5, "threads": 2, "chunk": 10})
    block = search.to_dict()
    assert [r["label"] for r in block["front"]] == ["base", "r1:b", "r1:a"]  # r1:c untimed
    assert [r["on_front"] for r in block["candidates"]] == [True, True, True, False]
    report = {"mode": "int8", "artifact": "step_int8.onnx", "search": block,
              "holdout": {"split": "val", "frames": 40, "mpjpe_mm": 10.0, "fp32_mpjpe_mm": 9.9, "bound_pct": 0.9}}
    md = markdown_report(report)
    row = next(line for line in md.splitlines() if line.startswith("| r1:b |"))
    assert row.split("|")[3:9] == [" 0.900 ", " 20.00 ", " 2.00 ", " yes ", " yes ", " **yes** "]
    write_search_outputs(report, tmp_path)
    assert (tmp_path / "report.md").read_text() == md
    assert (tmp_path / "front.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_pareto_front_matches_a_brute_force_reference():
    import itertools

    points = [(0.5, 30.0), (0.9, 20.0), (2.0, 10.0), (1.8, 25.0), (0.5, 31.0), (0.9, 20.0), (3.0, 10.0)]
    cands = [Candidate(f"c{i}", [], [], e, p50_ms=t) for i, (e, t) in enumerate(points)]
    cands.append(Candidate("untimed", [], [], 0.0))
    front = {c.label for c in pareto_front(cands)}
    # reference: a point is on the front unless another is no worse on both and better on one
    expected = {f"c{i}" for i, p in enumerate(points)
                if not any(q[0] <= p[0] and q[1] <= p[1] and q != p for q in points)}
    assert front == expected == {"c0", "c1", "c5", "c2"}
    assert not any(a == b for a, b in itertools.combinations(sorted(front), 2))


@pytest.mark.slow  # two INT8 quantisations of the trained tiny: ~85 s of CPU
def test_quantize_reports_the_front_and_builds_the_fastest_graph_within_budget(tmp_path, trained_graph,
                                                                            quant_data):  # noqa: F811
    """End to end on the trained tiny with injected timings that make the greedy choice the
    slowest timed candidate: the artifact must keep the faster within-budget candidate's
    groups in float instead, and report.json / report.md / front.png must show the front."""
    # A budget just below the base graph's distance (recurrence in float only, measured
    # first): most single groups kept in float lower it a little, so round 1 finds several
    # candidates within the budget while the base graph is outside it. No search margin: with
    # the INT8 default (0.25) the search aims a quarter below that budget, which one candidate
    # at most reaches. (Found failing on a vnni host on 2026-12-01, at HEAD and as far back as
    # 5ec3ab5^, with one candidate inside; the default test command deselects slow tests.)
    fast = dict(frames=16, holdout_frames=40)
    base = quantize_graph(trained_graph, quant_data, tmp_path / "base",
                          QuantizeOptions(mode="int8", exclude="recurrent", **fast))
    budget = 0.9999 * base["holdout"]["bound_pct"]

    def timer(graphs):  # the earlier a graph is handed over, the slower: the greedy choice comes first
        return {label: 100.0 * 0.8 ** i for i, label in enumerate(graphs)}  # 25% apart: no ties

    out = tmp_path / "int8"
    report = quantize_graph(trained_graph, quant_data, out,
                            QuantizeOptions(mode="int8", budget_pct=budget, max_rounds=1, search="groups",
                                            search_margin=0.0, **fast),
                            timer=timer)
    search = report["search"]
    inside = [c for c in search["candidates"] if c["within_budget"] and c["p50_ms"] is not None]
    assert len(inside) >= 2, "the fixture no longer gives two candidates within the budget"
    greedy_groups = min(inside, key=lambda c: c["distance_pct"])["float_groups"]
    fastest = min(inside, key=lambda c: c["p50_ms"])
    assert search["chosen"]["label"] == fastest["label"] and fastest["float_groups"] != greedy_groups
    assert report["quantization"]["float_groups"][-1] == fastest["float_groups"][-1]
    assert report["exclusion_search"]["chosen_groups"] == fastest["float_groups"]
    # the artifact is the chosen graph: its held-out distance is the candidate's
    # rel 1e-3: the artifact is written compacted (compact.py), and renaming can change the order
    # ONNX Runtime's optimisers visit float nodes in (float32 round-off); another graph differs by more
    assert report["holdout"]["bound_pct"] == pytest.approx(fastest["distance_pct"], rel=1e-3)
    timed = [c["p50_ms"] for c in search["candidates"] if c["p50_ms"] is not None]
    assert search["fp32_p50_ms"] is not None and search["front"][0]["p50_ms"] == min(timed)
    on_disk = json.loads((out / "report.json").read_text())
    assert on_disk["search"]["chosen"]["label"] == fastest["label"]
    md = (out / "report.md").read_text()
    assert "| candidate |" in md and fastest["label"] in md
    assert (out / "front.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_batchnorm_becomes_an_exact_depthwise_conv():
    """The pass against a numpy reference of inference-mode BatchNorm, on a graph that also
    uses the BN input elsewhere (the raw-input shortcut of a pre-activation block)."""
    import numpy as np
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    from e3dpsm.quantize.batchnorm import batchnorm_as_depthwise_conv

    rng = np.random.default_rng(3)
    c = 5
    gamma, beta = rng.normal(1, 0.5, c), rng.normal(0, 1, c)
    mean, var = rng.normal(0, 2, c), rng.uniform(0.1, 3.0, c)
    params = [numpy_helper.from_array(a.astype(np.float32), n)
              for a, n in zip((gamma, beta, mean, var), ("g", "b", "m", "v"))]
    nodes = [helper.make_node("BatchNormalization", ["x", "g", "b", "m", "v"], ["bn"], name="norm", epsilon=1e-3),
             helper.make_node("Sigmoid", ["bn"], ["sig"], name="act"),
             helper.make_node("Add", ["sig", "x"], ["y"], name="shortcut")]
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, c, 4, 6])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, c, 4, 6])], params)
    model = onnx.shape_inference.infer_shapes(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)],
                                                                ir_version=8))
    converted, count = batchnorm_as_depthwise_conv(model)
    assert count == 1 and [n.op_type for n in converted.graph.node] == ["Conv", "Sigmoid", "Add"]
    assert converted.graph.node[0].name == "norm" and converted.graph.node[0].output[0] == "bn"
    assert {i.name for i in converted.graph.initializer}.isdisjoint({"g", "b", "m", "v"})
    x = rng.normal(0, 3, (1, c, 4, 6)).astype(np.float32)
    shape = (1, c, 1, 1)
    bn = (x - mean.reshape(shape)) / np.sqrt(var.reshape(shape) + 1e-3) * gamma.reshape(shape) + beta.reshape(shape)
    expected = 1 / (1 + np.exp(-bn)) + x
    got = ort.InferenceSession(converted.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)
