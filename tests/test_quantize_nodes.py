"""`--exclude auto --search nodes`: rank compute nodes by their error when quantised alone,
then keep the fewest top-ranked ones in float that meet the budget. Error models injected,
checked against a brute-force reference; then once end to end on the tiny graph."""
from __future__ import annotations

import json
import math

import onnx
import pytest

from _quantize_helpers import FAST
from e3dpsm.errors import ConfigError
from e3dpsm.quantize import QuantizeOptions
from e3dpsm.quantize.exclusions import NodeRanking, node_sensitivity, ranked_prefix_exclusions
from e3dpsm.quantize.front import candidates_from_search, latency_aware_choice

# Per-node error when quantised alone; quantising several adds them in quadrature (what the
# trained `small` shows: root sum of squares 11.0% against 11.2% all quantised).
SOLO = {"n00": 0.1, "n01": 6.7, "n02": 0.3, "n03": 4.8, "n04": 3.7, "n05": 0.2, "n06": 2.5, "n07": 1.5,
        "n08": 0.05, "n09": 1.4, "n10": 0.6, "n11": 0.4}


def quadrature(excluded) -> float:
    return math.sqrt(sum(e * e for n, e in SOLO.items() if n not in excluded))


def brute_force_smallest_k(ranked, budget):
    return next(k for k in range(len(ranked) + 1) if quadrature(ranked[:k]) <= budget)


def test_sensitivity_ranks_highest_error_first():
    seen = []
    rows = node_sensitivity(list(SOLO), lambda node: seen.append(node) or SOLO[node])
    assert seen == list(SOLO)  # one trial per node
    assert [r["node"] for r in rows] == sorted(SOLO, key=lambda n: -SOLO[n])
    assert rows[0] == {"node": "n01", "error_pct": 6.7}


@pytest.mark.parametrize("budget", [0.5, 1.0, 2.0, 3.0, 5.0, 9.0, 20.0])
def test_prefix_search_finds_the_smallest_k_within_budget(budget):
    ranking = NodeRanking(node_sensitivity(list(SOLO), SOLO.__getitem__), frames=7)
    ranked = ranking.nodes
    calls = []

    def evaluate(excluded, label):
        calls.append(label)
        return quadrature(excluded)

    result = ranked_prefix_exclusions(["r1", "r2"], ranking, budget, evaluate)
    k = brute_force_smallest_k(ranked, budget)
    assert result.within_budget
    assert result.excluded_nodes == ["r1", "r2", *ranked[:k]]
    assert result.chosen == ([] if k == 0 else [f"top{k}"])
    assert result.error_pct == pytest.approx(quadrature(ranked[:k]))
    assert len(calls) == len(set(calls)) <= 1 + 2 * math.ceil(math.log2(len(ranked))) + 1  # doubling + bisection
    report = result.to_dict()
    assert report["strategy"] == "nodes" and report["sensitivity"] == ranking.rows and report["rank_frames"] == 7


def test_prefix_search_without_any_k_within_budget_returns_the_most_accurate():
    ranked = list(SOLO)
    ranking = NodeRanking([{"node": n, "error_pct": 0.0} for n in ranked])
    result = ranked_prefix_exclusions([], ranking, 0.01, lambda ex, label: 1.0 + 0.01 * abs(len(ex) - 5))
    assert not result.within_budget and result.error_pct == pytest.approx(1.0 + 0.01 * min(
        abs(t["float_nodes"] - 5) for t in result.trials))
    assert result.trials[-1]["float_nodes"] == len(ranked)  # it tried everything in float before giving up


def test_latency_objective_picks_the_faster_of_two_prefixes_within_budget():
    ranking = NodeRanking(node_sensitivity(list(SOLO), SOLO.__getitem__))
    built = []

    def evaluate(excluded, label):
        built.append((list(excluded), None))
        return quadrature(excluded)

    result = ranked_prefix_exclusions([], ranking, 2.0, evaluate)
    cands = candidates_from_search(result, built)
    for c in cands:
        c.path = f"/nowhere/{c.label}.onnx"
    inside = sorted((c for c in cands if c.error_pct <= 2.0), key=lambda c: len(c.excluded_nodes))
    assert len(inside) >= 2 and inside[0].label == result.chosen[0]
    # the larger prefix is faster here (say its float nodes are cheap and spare Q/DQ hops)
    ms = {c.label: 10.0 for c in cands}
    ms[inside[0].label], ms[inside[1].label] = 12.0, 8.0
    choice = latency_aware_choice(result, cands, lambda graphs: {k: ms[k] for k in graphs if k in ms},
                                  "latency", 2.0, max_timed=10)
    assert choice.chosen.label == inside[1].label
    accurate = latency_aware_choice(result, cands, None, "accuracy", 2.0)
    assert accurate.chosen.label == inside[0].label


def _holdout(sequences: int = 2, frames: int = 10):
    import numpy as np

    from e3dpsm.quantize.holdout import HoldoutSet

    rng = np.random.default_rng(0)
    gt = [rng.normal(size=(frames, 16, 3)) * 100 for _ in range(sequences)]
    outputs = [{name: g + rng.normal(size=g.shape) * scale for name, scale in
                (("pose", 30.0), ("pose_direct", 40.0), ("pose_delta", 50.0))} for g in gt]
    lnes = [rng.random((frames, 2, 4, 4)).astype(np.float32) for _ in range(sequences)]
    return HoldoutSet(lnes, gt, outputs, 20.0)


def test_holdout_head_is_the_first_frames_of_every_stream():
    import numpy as np

    from e3dpsm.metrics import mpjpe

    full = _holdout()
    head = full.head(4)
    assert head.frames == 8 and head.window_ms == full.window_ms
    for h, f in zip(head.fp32_outputs, full.fp32_outputs):
        assert set(h) == set(f) and all(np.array_equal(h[k], f[k][:4]) for k in f)
    expected = mpjpe(np.concatenate([o["pose"][:4] for o in full.fp32_outputs]),
                     np.concatenate([g[:4] for g in full.gt]))
    assert head.fp32_mpjpe == pytest.approx(expected) and head.fp32_mpjpe != pytest.approx(full.fp32_mpjpe)
    assert full.head(100).frames == full.frames  # longer than the streams: all of them
    with pytest.raises(ValueError):
        full.head(0)


@pytest.mark.parametrize("rank_frames, per_sequence", [(4, 4), (0, 10)])
def test_ranking_runs_on_the_head_of_the_held_out_streams(rank_frames, per_sequence):
    """The solo trials see only `rank_frames` per sequence (0: all); each quantises exactly
    its own node; the rows come back highest error first."""
    from e3dpsm.quantize.api import rank_nodes

    seen_frames, trials = [], []

    def make_evaluator(subset):
        seen_frames.append(subset.frames)

        def evaluate(excluded, label):
            quantised = [n for n in SOLO if n not in excluded]
            trials.append((label, quantised))
            return SOLO[quantised[0]]
        return evaluate

    ranking = rank_nodes(list(SOLO), list(SOLO), _holdout(), rank_frames, make_evaluator)
    rows = ranking.rows
    assert seen_frames == [2 * per_sequence] and ranking.frames == per_sequence
    assert all(quantised == [label.removeprefix("alone_")] for label, quantised in trials) and len(trials) == len(SOLO)
    assert [r["node"] for r in rows] == sorted(SOLO, key=lambda n: -SOLO[n])


def test_rank_frames_must_not_be_negative():
    with pytest.raises(ConfigError, match="rank-frames"):
        QuantizeOptions(mode="int8", rank_frames=-1)


def test_nodes_search_is_int8_only():
    assert QuantizeOptions(mode="int8").strategy == "nodes"
    assert QuantizeOptions(mode="fp16").strategy == "groups"
    with pytest.raises(ConfigError, match="--search nodes ranks INT8 nodes"):
        QuantizeOptions(mode="fp16", search="nodes")
    with pytest.raises(ConfigError, match="unknown search"):
        QuantizeOptions(mode="int8", search="layers")
    with pytest.raises(ConfigError, match="drop it with --exclude recurrent"):
        QuantizeOptions(mode="int8", exclude="recurrent", search="groups")


def test_nodes_search_end_to_end_on_the_trained_tiny(int8_dir, int8_test_budget_pct, trained_graph):  # noqa: F811
    """The shared INT8 fixture runs the default search (nodes) with a budget of half the
    graph's error with only the recurrence in float (measured on this host): the search must
    keep some, not all, ranked nodes in float, and the artifact must be the graph it measured."""
    report = json.loads((int8_dir / "report.json").read_text())
    search = report["exclusion_search"]
    ranked = search["sensitivity"]
    ops = {n.name: n.op_type for n in onnx.load(str(trained_graph)).graph.node}
    assert search["strategy"] == "nodes" and len(ranked) >= 10
    assert search["rank_frames"] == FAST["rank_frames"] < FAST["holdout_frames"]
    assert all(ops.get(r["node"], "Conv") in ("Conv", "MatMul", "Gemm") for r in ranked)
    assert [r["error_pct"] for r in ranked] == sorted((r["error_pct"] for r in ranked), reverse=True)
    assert search["trials"][0]["error_pct"] > int8_test_budget_pct
    k = int(search["chosen_groups"][0][3:])
    assert 0 < k < len(ranked) and search["within_budget"]
    float_kept = set(report["excluded_nodes"])
    # The prefix leaves 8 bits: to float, or to 16-bit activations (and weights) (precision.py).
    out_of_int8 = float_kept | set(report["quantization"]["int16_nodes"]) | set(report["quantization"]["int16w16_nodes"])
    assert {r["node"] for r in ranked[:k]} <= out_of_int8 and not {r["node"] for r in ranked[k:]} & out_of_int8
    # the written graph is the measured one: its held-out error is the search's (after the
    # int16 step), the largest distance over the pose outputs (what `golden check` holds each of them to)
    holdout = report["holdout"]
    # rel 1e-3: the artifact is written compacted (compact.py), and renaming can change the order
    # ONNX Runtime's optimisers visit float nodes in (float32 round-off); another graph differs by more
    assert holdout["bound_pct"] == pytest.approx(report["precision_search"]["error_pct"], rel=1e-3)
    assert set(holdout["deviation_by_output_mm"]) == {"pose", "pose_direct", "pose_delta"}
    assert holdout["bound_pct"] == pytest.approx(
        100 * max(holdout["deviation_by_output_mm"].values()) / holdout["fp32_mpjpe_mm"], rel=1e-9)
    model = onnx.load(str(int8_dir / "step_int8.onnx"))
    dq_inputs = {n.output[0] for n in model.graph.node if n.op_type == "DequantizeLinear"}
    for node in model.graph.node:  # ranked nodes outside the prefix run on dequantised inputs, the prefix on float
        if node.name in {r["node"] for r in ranked}:
            assert (node.input[0] in dq_inputs) == (node.name not in float_kept), node.name
    md = (int8_dir / "report.md").read_text()
    assert "## Node sensitivity" in md and f"`{ranked[0]['node']}`" in md
