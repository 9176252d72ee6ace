"""int16 in the precision search: 16-bit activation QDQ runs on ONNX Runtime in the default
domain (opset 21) and is closer to fp32 than the same nodes at 8 bits; the per-node choice
int8 -> int16 -> float on injected errors; the default search reports where nodes ended."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from e3dpsm.quantize.precision import PRECISIONS, choose_precision, demote_to_int16


# -- the pure choice, on injected errors ---------------------------------------------------

def test_choice_prefers_int16_over_float_when_both_meet_the_budget() -> None:
    choice = choose_precision("conv7", {"int8": 1.4, "int16": 0.8, "float": 0.6}, 1.0)
    assert choice.precision == "int16" and "int8 1.400% over" in choice.reason
    assert choose_precision("conv7", {"int16": 0.99, "float": 0.2}, 1.0).precision == "int16"


def test_choice_takes_int8_when_it_meets_the_budget_and_float_when_int16_does_not() -> None:
    assert choose_precision("n", {"int8": 0.7, "int16": 0.5, "float": 0.4}, 1.0).precision == "int8"
    assert choose_precision("n", {"int8": 1.7, "int16": 1.2, "float": 0.9}, 1.0).precision == "float"
    assert choose_precision("n", {"int16": 1.0, "float": 0.3}, 1.0).precision == "int16"  # the budget is inclusive


def test_choice_without_any_precision_in_budget_is_the_most_accurate() -> None:
    choice = choose_precision("n", {"int8": 3.0, "int16": 1.5, "float": 1.6}, 1.0)
    assert choice.precision == "int16" and "no precision meets" in choice.reason
    with pytest.raises(ValueError):
        choose_precision("n", {"int4": 0.1}, 1.0)
    assert PRECISIONS == ("int8", "int16", "int16w16", "float")
    assert choose_precision("n", {"int16": 1.3, "int16w16": 0.7, "float": 0.6}, 1.0).precision == "int16w16"


def test_demotion_keeps_each_node_at_int16_where_the_graph_stays_within_budget() -> None:
    # Injected model of the graph error: each node at int16 adds its cost, in float nothing.
    cost16 = {"a": 0.5, "b": 0.05, "c": 0.3, "d": 0.2}
    base = 0.4

    def evaluate(int16: list[str], floats: list[str], label: str) -> float:
        assert not set(int16) & set(floats) and set(int16) | set(floats) == set(cost16)
        return base + sum(cost16[n] for n in int16)

    # With the whole budget to spend: all at int16 is 1.45 > 1.0; then least sensitive first:
    # d (0.6), c (0.9), b (0.95), a (1.45: float).
    plan = demote_to_int16(["a", "b", "c", "d"], base, 1.0, evaluate, slack_share=1.0)
    assert plan.int16 == ["d", "c", "b"] and plan.float_nodes == ["a"]
    assert plan.error_pct == pytest.approx(0.95)
    by_node = {c.node: c for c in plan.choices}
    assert by_node["a"].precision == "float" and by_node["a"].errors == {"int16": pytest.approx(1.45), "float": pytest.approx(0.95)}
    assert [t["label"] for t in plan.trials] == ["int16_all", "int16_d", "int16_c", "int16_b", "int16_a"]
    # By default only half the slack (target 0.4 + 0.5 x 0.6 = 0.7): d (0.6), c (0.9: float),
    # b (0.65), a (1.15: float).
    plan = demote_to_int16(["a", "b", "c", "d"], base, 1.0, evaluate)
    assert plan.target_pct == pytest.approx(0.7) and plan.int16 == ["d", "b"] and plan.float_nodes == ["a", "c"]
    assert plan.error_pct == pytest.approx(0.65)

    cheap = demote_to_int16(["a", "b"], base, 1.0, lambda i, f, l: base + 0.01 * len(i))
    assert cheap.int16 == ["a", "b"] and len(cheap.trials) == 1  # one trial when all fit at once


def test_demotion_reuses_a_measured_all_int16_error() -> None:
    calls: list[str] = []

    def evaluate(int16: list[str], floats: list[str], label: str) -> float:
        calls.append(label)
        return 0.4 + 0.2 * len(int16)

    plan = demote_to_int16(["a", "b"], 0.4, 1.0, evaluate, all_int16_error_pct=0.55)
    assert calls == [] and plan.int16 == ["a", "b"] and plan.error_pct == 0.55
    assert plan.trials == [{"label": "int16_all", "int16_nodes": 2, "float_nodes": 0, "error_pct": 0.55}]
    over = demote_to_int16(["a", "b"], 0.4, 1.0, evaluate, all_int16_error_pct=0.9)  # 0.9 > 0.7: one at a time
    assert calls == ["int16_b", "int16_a"] and over.int16 == ["b"]  # b 0.6, then a 0.8 > 0.7


def test_size_objective_takes_the_fewest_nodes_that_all_fit_at_int16() -> None:
    from e3dpsm.quantize.precision import smallest_int16_plan

    # Injected: a candidate's all-int16 error is its float error plus 0.01 per node at int16
    # times a per-node cost that falls with the candidate's size (the most sensitive nodes
    # are in every candidate; a larger one leaves more slack).
    candidates = [("top64", [f"n{i}" for i in range(64)], 0.30), ("top37", [f"n{i}" for i in range(37)], 0.736),
                  ("top48", [f"n{i}" for i in range(48)], 0.48), ("top40", [f"n{i}" for i in range(40)], 0.69),
                  ("top32", [f"n{i}" for i in range(32)], 0.87)]  # over the 0.75 target: never probed
    measured = {"top37": 0.784, "top40": 0.76, "top48": 0.588, "top64": 0.35}
    asked: list[str] = []

    def evaluate(int16: list[str], label: str) -> float:
        name = label.removeprefix("int16_all_")
        asked.append(name)
        assert int16 == next(nodes for lab, nodes, _ in candidates if lab == name)
        return measured[name]

    index, probes = smallest_int16_plan(candidates, 0.75, evaluate)
    # targets 0.736 + 0.5 x 0.014 = 0.743 (0.784: no), 0.69 + 0.03 = 0.72 (0.76: no), 0.48 + 0.135 = 0.615 (0.588: yes)
    assert candidates[index][0] == "top48" and asked == ["top37", "top40", "top48"]
    assert [p.fits for p in probes] == [False, False, True]
    assert probes[0].target_pct == pytest.approx(0.743) and probes[-1].to_dict()["fits"] is True
    # Near the threshold: top48 at exactly its target fits, a hair over does not (then top64)
    measured["top48"] = 0.48 + 0.5 * (0.75 - 0.48)
    assert candidates[smallest_int16_plan(candidates, 0.75, evaluate)[0]][0] == "top48"
    measured["top48"] += 1e-6
    assert candidates[smallest_int16_plan(candidates, 0.75, evaluate)[0]][0] == "top64"
    base = [("base", [], 0.5), *candidates]  # nothing out of 8 bits: fits without a graph built
    asked.clear()
    index, probes = smallest_int16_plan(base, 0.75, evaluate)
    assert index == 0 and asked == [] and probes[0].int16_error_pct == 0.5 and probes[0].fits
    measured.update(top64=0.9)  # none fits: no choice, every probe reported
    index, probes = smallest_int16_plan(candidates, 0.75, evaluate)
    assert index is None and [p.label for p in probes] == ["top37", "top40", "top48", "top64"]


def test_size_objective_needs_an_int16_search() -> None:
    from e3dpsm.errors import ConfigError
    from e3dpsm.quantize import QuantizeOptions

    assert QuantizeOptions(mode="int8").search_objective == "size"
    assert QuantizeOptions(mode="int8", int16=False).search_objective == "latency"
    assert QuantizeOptions(mode="fp16").search_objective == "latency"
    assert QuantizeOptions(mode="int8", objective="accuracy").search_objective == "accuracy"
    for kwargs in ({"int16": False}, {"mode": "fp16"}, {"exclude": "recurrent"}, {"search": "groups"}):
        with pytest.raises(ConfigError, match="--objective size"):
            QuantizeOptions(**{"mode": "int8", **kwargs, "objective": "size"})


def test_promotion_gives_float_nodes_16_bit_weights_where_the_graph_stays_within_target() -> None:
    from e3dpsm.quantize.precision import PrecisionChoice, PrecisionPlan, promote_to_int16w16

    # Injected: each node in float adds nothing, at int16w16 its cost; two int16 nodes fixed.
    cost = {"a": 0.25, "b": 0.02, "c": 0.1}
    base = 0.5

    def evaluate(int16: list[str], w16: list[str], floats: list[str], label: str) -> float:
        assert int16 == ["x", "y"] and not set(w16) & set(floats) and set(w16) | set(floats) == set(cost)
        return base + sum(cost[n] for n in w16)

    choices = [PrecisionChoice(n, "float", "int16 over", {"int16": 2.0, "float": base}) for n in cost]
    plan = PrecisionPlan(["x", "y"], ["a", "b", "c"], base, choices, [{"label": "int16_all"}], target_pct=0.7)
    # All at once: 0.87 > 0.7; then least sensitive first: c (0.6), b (0.62), a (0.87: float).
    promoted = promote_to_int16w16(plan, evaluate)
    assert promoted.int16w16 == ["b", "c"] and promoted.float_nodes == ["a"] and promoted.int16 == ["x", "y"]
    assert promoted.error_pct == pytest.approx(0.62)
    by_node = {c.node: c for c in promoted.choices}
    assert by_node["c"].precision == "int16w16" and by_node["c"].errors["int16w16"] == pytest.approx(0.6)
    assert by_node["a"].precision == "float" and "int16w16 0.870% over" in by_node["a"].reason
    assert [t["label"] for t in promoted.trials] == ["int16_all", "int16w16_all", "int16w16_c", "int16w16_b", "int16w16_a"]
    assert promoted.to_dict()["int16w16_nodes"] == ["b", "c"]

    cheap = promote_to_int16w16(plan, lambda i, w, f, l: base + 0.01 * len(w))
    assert cheap.int16w16 == ["a", "b", "c"] and not cheap.float_nodes and len(cheap.trials) == 2
    untouched = PrecisionPlan(["x"], [], 0.3, [], [], target_pct=0.7)
    assert promote_to_int16w16(untouched, evaluate) is untouched  # nothing in float: no trial


# -- on ONNX Runtime ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def int16_setup(tmp_path_factory, trained_graph: Path, quant_data: Path, calibrated_tiny: dict) -> dict:
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.quantize.graph_groups import recurrent_groups
    from e3dpsm.quantize.holdout import make_holdout

    model = onnx.load(str(calibrated_tiny["pre"]))
    keep = [n for g in recurrent_groups(model, GraphMetadata.from_onnx(model)) for n in g.nodes]
    holdout = make_holdout(trained_graph, PreparedData.open(quant_data).split("val"), 20.0, 40, 1)
    kept = set(keep)
    compute = [n.name for n in model.graph.node if n.op_type in ("Conv", "MatMul", "Gemm") and n.name not in kept]
    return {"work": tmp_path_factory.mktemp("int16"), "pre": calibrated_tiny["pre"], "keep": keep,
            "cache": calibrated_tiny["cache"], "holdout": holdout, "compute": compute,
            "meta": GraphMetadata.from_onnx(onnx.load(str(trained_graph)))}


def _quantised(setup: dict, int16: list[str], name: str) -> tuple[Path, onnx.ModelProto]:
    from e3dpsm.quantize.artifact import finalize, save_model
    from e3dpsm.quantize.static import StaticConfig, quantize_int8

    out = setup["work"] / name
    quantize_int8(setup["pre"], out, StaticConfig(), exclude=setup["keep"], cache=setup["cache"], int16_nodes=int16)
    model = onnx.load(str(out))
    finalize(model, setup["meta"], {"mode": "int8"})
    save_model(model, out)
    return out, onnx.load(str(out))


def test_int16_nodes_run_on_onnx_runtime_closer_to_fp32_than_int8(int16_setup) -> None:
    from e3dpsm.quantize.holdout import accuracy_of

    # The CNN's convolutions (half the compute nodes) at 16-bit activations, the rest at 8.
    convs = [n for n in int16_setup["compute"] if "/stages." in n or "/stem/" in n]
    assert len(convs) >= 10
    path16, model16 = _quantised(int16_setup, convs, "int16.onnx")
    path8, model8 = _quantised(int16_setup, [], "int8.onnx")
    # Standard ONNX only: default-domain Q/DQ at opset 21, 16-bit zero points on those nodes' tensors.
    assert {n.domain for n in model16.graph.node} == {""}
    assert next(o.version for o in model16.opset_import if o.domain == "") == 21
    inits = {i.name: numpy_helper.to_array(i) for i in model16.graph.initializer}
    zp = {n.input[0]: inits[n.input[2]].dtype for n in model16.graph.node if n.op_type == "QuantizeLinear"}
    first_conv_input = next(n.input[0] for n in onnx.load(str(int16_setup["pre"])).graph.node if n.name == convs[0])
    assert zp[first_conv_input] == np.uint16
    assert sum(d == np.uint16 for d in zp.values()) >= len(convs) and any(d == np.uint8 for d in zp.values())
    # Fewer 8-bit tensors than the all-int8 graph, the same Q/DQ count.
    assert len([d for d in zp.values() if d == np.uint8]) < sum(1 for n in model8.graph.node if n.op_type == "QuantizeLinear")
    err16 = accuracy_of(path16, int16_setup["holdout"], 1)["bound_pct"]
    err8 = accuracy_of(path8, int16_setup["holdout"], 1)["bound_pct"]
    # Measured on an AMD EPYC with AVX-512 VNNI: ~1.3% against 2.08%. Rounding 256x finer on
    # half the tensors must remove a clear share of the error on any CPU kind (int16 nodes
    # run in float arithmetic behind their DequantizeLinear; no VNNI dependence).
    assert err16 < 0.85 * err8, (err16, err8)


def test_int16w16_nodes_read_16_bit_weights_rounded_to_their_own_scale(int16_setup) -> None:
    from e3dpsm.quantize.artifact import finalize, save_model
    from e3dpsm.quantize.holdout import accuracy_of
    from e3dpsm.quantize.static import StaticConfig, quantize_int8

    convs = [n for n in int16_setup["compute"] if "/stages." in n or "/stem/" in n][:6]
    out = int16_setup["work"] / "int16w16.onnx"
    quantize_int8(int16_setup["pre"], out, StaticConfig(), exclude=int16_setup["keep"], cache=int16_setup["cache"],
                  int16w16_nodes=convs)
    model = onnx.load(str(out))
    finalize(model, int16_setup["meta"], {"mode": "int8"})
    save_model(model, out)
    pre = {n.name: n for n in onnx.load(str(int16_setup["pre"])).graph.node}
    floats = {i.name: numpy_helper.to_array(i) for i in onnx.load(str(int16_setup["pre"])).graph.initializer}
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    conv_of = {n.name: n for n in model.graph.node}
    producer = {o: n for n in model.graph.node for o in n.output}
    for name in convs:
        dq = producer[conv_of[name].input[1]]
        assert dq.op_type == "DequantizeLinear"
        q, scale = inits[dq.input[0]], inits[dq.input[1]]
        assert q.dtype == np.int16 and not np.any(inits[dq.input[2]])  # symmetric: zero point 0
        w = floats[pre[name].input[1]].astype(np.float64)
        # numpy: symmetric 16-bit rounding of the float weight at the graph's scale (per tensor
        # as asked, or per channel if ONNX Runtime widened one for its int32 bias check)
        shape = (-1,) + (1,) * (w.ndim - 1)
        s64 = np.asarray(scale, np.float64).reshape(shape if np.ndim(scale) else ())
        if not np.ndim(scale):  # per tensor, as asked (ORT may widen it for its int32 bias check)
            assert float(scale) >= np.abs(w).max() / 32767 * (1 - 1e-6)
        # ONNX Runtime divides in float32 (float64 rounds a handful of half-way values the other way)
        w32, s32 = w.astype(np.float32), s64.astype(np.float32)
        np.testing.assert_array_equal(q, np.clip(np.round(w32 / s32), -32768, 32767).astype(np.int16))
        assert np.abs(q.astype(np.float64) * s64 - w).max() <= 0.51 * float(np.max(s64))  # half a step, float32
    err = accuracy_of(out, int16_setup["holdout"], 1)["bound_pct"]
    err16 = accuracy_of(_quantised(int16_setup, convs, "int16_same.onnx")[0], int16_setup["holdout"], 1)["bound_pct"]
    # 16-bit weights on top of 16-bit activations: the same nodes' weight rounding gone; the
    # graph's other 8-bit nodes dominate, so only require it not to be worse beyond noise.
    assert err <= 1.05 * err16, (err, err16)


def test_reduced_range_targets_give_16_bit_nodes_full_range_weights(int16_setup) -> None:
    """Under reduce_range (an AVX2 target) only nodes with 8-bit activations reach the U8S8
    kernels the 7-bit range guards: 16-bit nodes' weights take the full range (8-bit weights
    +-127 per channel, 16-bit weights +-32767), the others stay within +-64."""
    from e3dpsm.quantize.static import StaticConfig, quantize_int8

    convs = [n for n in int16_setup["compute"] if "/stages." in n or "/stem/" in n]
    int16, w16, int8 = convs[:3], convs[3:5], convs[5:8]
    out = int16_setup["work"] / "reduced.onnx"
    quantize_int8(int16_setup["pre"], out, StaticConfig(reduce_range=True), exclude=int16_setup["keep"],
                  cache=int16_setup["cache"], int16_nodes=int16, int16w16_nodes=w16)
    model = onnx.load(str(out))
    pre = {n.name: n for n in onnx.load(str(int16_setup["pre"])).graph.node}
    floats = {i.name: numpy_helper.to_array(i) for i in onnx.load(str(int16_setup["pre"])).graph.initializer}
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    node_of = {n.name: n for n in model.graph.node}
    producer = {o: n for n in model.graph.node for o in n.output}

    def weight(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        dq = producer[node_of[name].input[1]]
        return inits[dq.input[0]], np.asarray(inits[dq.input[1]], np.float32), floats[pre[name].input[1]]

    for name in int16:
        q, scale, w = weight(name)
        assert q.dtype == np.int8
        channel_max = np.abs(q.reshape(q.shape[0], -1)).max(axis=1)
        assert channel_max.max() == 127, (name, channel_max.max())
        # numpy: symmetric per-channel scale max|w| / 127 (ONNX Runtime's full 8-bit range)
        expected = (np.abs(w.reshape(w.shape[0], -1)).max(axis=1) / 127).astype(np.float32)
        np.testing.assert_allclose(scale, expected, rtol=1e-6)
    for name in w16:
        q, scale, w = weight(name)
        assert q.dtype == np.int16 and np.abs(q).max() > 16384, (name, np.abs(q).max())
    for name in int8:
        q, _, _ = weight(name)
        assert q.dtype == np.int8 and np.abs(q).max() <= 64, (name, np.abs(q).max())


def test_default_search_reports_each_node_precision(int8_dir: Path) -> None:
    report = json.loads((int8_dir / "report.json").read_text())
    q = report["quantization"]
    plan = report["precision_search"]
    out_of_int8 = [c["node"] for c in plan["choices"] if c["precision"] != "int8"]
    assert sorted(plan["int16_nodes"] + plan["int16w16_nodes"] + plan["float_nodes"]) == sorted(out_of_int8)
    assert q["int16_nodes"] == plan["int16_nodes"] and q["int16w16_nodes"] == plan["int16w16_nodes"]
    budget = q["budget_pct"]
    for choice in plan["choices"]:
        # int8: only a recurrent group's projection (precision.quantise_recurrent_compute)
        assert choice["precision"] in ("int16", "int16w16", "float") or (
            choice["precision"] == "int8" and choice["reason"].startswith("recurrent group: "))
        assert choice["reason"] and choice["errors"]
        assert (choice["node"] in plan["int8_recurrent_nodes"]) == (choice["precision"] == "int8")
        if choice["precision"] != "float":  # kept below float only where the graph met the target so
            assert choice["errors"][choice["precision"]] <= plan["target_pct"] <= budget
    # The default objective under int16 is size (precision.smallest_int16_plan): candidates
    # within the target probed fewest nodes first, up to the first whose nodes all fit at int16.
    assert report["search"]["objective"] == "size"
    probes = plan["size_probes"]
    assert [p["nodes"] for p in probes] == sorted(p["nodes"] for p in probes)
    assert all(p["fits"] == (p["int16_error_pct"] <= p["target_pct"]) for p in probes)
    assert not any(p["fits"] for p in probes[:-1])
    ranked_choices = [c for c in plan["choices"] if not c["reason"].startswith("recurrent group: ")]
    if probes and probes[-1]["fits"]:
        assert report["search"]["chosen"]["label"] == probes[-1]["label"]
        assert len(ranked_choices) == probes[-1]["nodes"] and all(c["precision"] == "int16" for c in ranked_choices)
        assert "Objective size: " in (int8_dir / "report.md").read_text()
    if out_of_int8:  # report.md says where each went
        text = (int8_dir / "report.md").read_text()
        assert f"## Precision per node ({len(out_of_int8)} nodes out of 8 bits" in text
        assert all(f"| `{c['node']}` | {c['precision']} |" in text for c in plan["choices"])
    model = onnx.load(str(int8_dir / report["artifact"]))
    opset = next(o.version for o in model.opset_import if o.domain == "")
    # The attention origins the pre-pass folded back are stored as a block and a Tile again.
    retiled = report["sizes"]["retiled_constants"]
    assert retiled["constants"] == sum(n.op_type == "Tile" and n.name.endswith("::tile") for n in model.graph.node) >= 1
    assert {n.domain for n in model.graph.node} == {""}
    assert (opset >= 21) == bool(plan["int16_nodes"])  # only graphs with 16-bit nodes leave the export's opset
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    producer = {o: n for n in model.graph.node for o in n.output}
    for node in (n for n in model.graph.node if n.name in set(plan["int16w16_nodes"])):
        assert inits[producer[node.input[1]].input[0]].dtype == np.int16  # its weight, through its DequantizeLinear
    # The census read off the artifact agrees with the plan: each planned node computes at its
    # precision; an unplanned one is int8, or int16 where it reads a tensor a 16-bit node widened.
    from e3dpsm.quantize.census import compute_precisions, precision_counts

    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.quantize.graph_groups import recurrent_groups

    source = onnx.load(report["config"]["model"])
    recurrent = {n for g in recurrent_groups(source, GraphMetadata.from_onnx(source)) for n in g.nodes}
    census = compute_precisions(model)
    assert any(n in recurrent for n in census)  # S5's projections, the fusion's Gemms
    # The recurrent groups' projections are decided (int16, int16w16 or float, each with its
    # reason) unless the plan had no slack left; undecided, they stay in float.
    decided = [c["node"] for c in plan["choices"] if c["reason"].startswith("recurrent group: ")]
    assert set(decided) <= recurrent and (decided or plan["error_pct"] > plan["target_pct"])
    # S5's readouts read the state the step outputs: decided too, through a copy of it
    states = {o.name for o in source.graph.output}
    readouts = {n.name for n in source.graph.node if n.name in recurrent and n.op_type in ("MatMul", "Gemm")
                and set(n.input) & states}
    assert readouts and (not decided or readouts <= set(decided)) and set(q["state_reads"]) == readouts
    planned = {**dict.fromkeys(plan["int16_nodes"], "int16"), **dict.fromkeys(plan["int16w16_nodes"], "int16w16"),
               **dict.fromkeys(plan["float_nodes"], "float"), **dict.fromkeys(plan["int8_recurrent_nodes"], "int8")}
    for node, label in census.items():
        if node in planned:  # a recurrent node at int8 too: none reads a tensor a 16-bit node widened
            assert label == planned[node], (node, label)
        elif node in recurrent:
            assert not decided and label == "float", (node, label)
        else:  # int16 where it reads a tensor a 16-bit node widened
            assert label in ("int8", "int16"), (node, label)
    assert q["compute_precision"] == precision_counts(census)
    assert q["compute_nodes_out_of_8_bits"] == sum(1 for label in census.values() if label != "int8")
    # 16-bit nodes' 8-bit weights take the full range even where the target reduces it (an
    # AVX2 target; static.full_range_weight_overrides), rounded by AdaRound at that range.
    source_weights = {i.name: numpy_helper.to_array(i) for i in source.graph.initializer}
    source_nodes = {n.name: n for n in source.graph.node}
    adarounded = 0
    for node in (n for n in model.graph.node if n.name in set(plan["int16_nodes"])):
        dq = producer[node.input[1]]
        ints, scale = inits[dq.input[0]], inits[dq.input[1]]
        if ints.dtype != np.int8:
            continue
        assert np.abs(ints).max() == 127, (node.name, np.abs(ints).max())
        w = source_weights.get(source_nodes[node.name].input[1]) if node.name in source_nodes else None
        if w is not None and w.shape == ints.shape and np.ndim(scale) == 1:
            shape = (-1,) + (1,) * (w.ndim - 1) if node.op_type == "Conv" else (1, -1)
            nearest = np.round(w.astype(np.float32) / scale.astype(np.float32).reshape(shape))
            adarounded += not np.array_equal(ints, nearest)
    if q["reduce_range"]:  # the 8-bit nodes' weights stay 7-bit
        for node in (n for n in model.graph.node if census.get(n.name) == "int8"):
            dq = producer.get(node.input[1])
            if dq is not None and dq.input[0] in inits:
                assert np.abs(inits[dq.input[0]]).max() <= 64, node.name
    if plan["int16_nodes"] and report.get("weight_rounding", {}).get("method") == "adaround":
        assert adarounded >= 1  # not left at nearest rounding
    # The artifact itself was timed beside fp32, and the verdict speaks of that timing.
    from e3dpsm.quantize.front_report import speed_verdict

    timing = report["artifact_timing"]
    assert timing["p50_ms"] > 0 and timing["speedup_vs_fp32"] == pytest.approx(timing["fp32_p50_ms"] / timing["p50_ms"])
    assert f"{timing['fp32_p50_ms'] / timing['p50_ms']:.2f}x" in speed_verdict(report)
    if out_of_int8:  # the artifact is the graph the last decision measured
        # rel 1e-3: the artifact is written compacted (compact.py), and renaming can change the order
        # ONNX Runtime's optimisers visit float nodes in (float32 round-off); another graph differs by more
        assert report["holdout"]["bound_pct"] == pytest.approx(plan["error_pct"], rel=1e-3)


def test_int16_tensors_take_the_widened_min_max_range_under_mse_calibration(int16_setup, trained_graph: Path,
                                                                             quant_data: Path) -> None:
    """The mse ranges are chosen for 256 levels (clipping buys a finer step); at 65,536 levels
    clipping is all the error left, so 16-bit tensors get the calibration's full min-max range,
    widened INT16_RANGE_MARGIN times (unseen sequences go past the calibration's range)."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize.calibration import record_calibration_set
    from e3dpsm.quantize.static import INT16_RANGE_MARGIN, StaticConfig, calibrate, minmax_cache_path, quantize_int8

    work = int16_setup["work"]
    calib = record_calibration_set(trained_graph, PreparedData.open(quant_data).split("train"), 16, 20.0, threads=1)
    cache = work / "cache_mse.json"
    chosen = calibrate(int16_setup["pre"], StaticConfig(calibration="mse"), calib, cache)
    minmax = json.loads(minmax_cache_path(cache).read_text())["data"]
    pre = onnx.load(str(int16_setup["pre"]))
    # A conv whose input range the mse rule narrowed: there the two rules differ.
    node, tensor = next((n.name, n.input[0]) for n in pre.graph.node
                        if n.name in int16_setup["compute"] and n.input[0] in chosen and chosen[n.input[0]].kind != "minmax")
    out = work / "mse16.onnx"
    quantize_int8(int16_setup["pre"], out, StaticConfig(calibration="mse"), exclude=int16_setup["keep"], cache=cache,
                  int16_nodes=[node])
    model = onnx.load(str(out))
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    q = next(n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == tensor)
    low, high = min(minmax[tensor]["lowest"]["data"][0], 0.0), max(minmax[tensor]["highest"]["data"][0], 0.0)
    low, high = low * INT16_RANGE_MARGIN, high * INT16_RANGE_MARGIN
    assert INT16_RANGE_MARGIN > 1.0
    assert inits[q.input[2]].dtype == np.uint16
    assert float(inits[q.input[1]]) == pytest.approx((high - low) / 65535, rel=1e-5)
    narrowed = (chosen[tensor].high - chosen[tensor].low) / 65535
    assert abs(float(inits[q.input[1]]) - narrowed) > 1e-3 * narrowed


@pytest.mark.parametrize("low, high, margin, expected", [
    (-1.0, 3.0, 2.0, (-2.0, 6.0)),
    (0.5, 4.0, 2.0, (0.0, 8.0)),      # zero joins the range first, as in every QDQ range
    (-3.0, -1.0, 1.5, (-4.5, 0.0)),
    (-1.0, 3.0, 1.0, (-1.0, 3.0)),
])
def test_widened_range(low: float, high: float, margin: float, expected: tuple[float, float]) -> None:
    from e3dpsm.quantize.static import widened_range

    assert widened_range(low, high, margin) == pytest.approx(expected)


def test_widened_range_refuses_a_margin_that_clips() -> None:
    from e3dpsm.quantize.static import widened_range

    with pytest.raises(ValueError, match="margin below 1"):
        widened_range(-1.0, 1.0, 0.5)


def test_int16_tensors_are_widened_under_minmax_calibration_too(tmp_path: Path) -> None:
    """Without an mse cache the calibration cache's own range is widened (it used to be
    written as it was, clipping unseen sequences)."""
    from e3dpsm.quantize.static import INT16_RANGE_MARGIN, int16_ranges

    cache = tmp_path / "calibration.json"
    cache.write_text(json.dumps({"data": {"a": {"lowest": {"data": [-0.5]}, "highest": {"data": [2.0]}},
                                          "b": {"lowest": {"data": [1.0]}, "highest": {"data": [3.0]}}}}))
    ranges = int16_ranges(cache, ["a", "b", "missing"])
    assert ranges == {"a": pytest.approx((-0.5 * INT16_RANGE_MARGIN, 2.0 * INT16_RANGE_MARGIN)),
                      "b": pytest.approx((0.0, 3.0 * INT16_RANGE_MARGIN))}


def test_weight_overrides_name_each_weight_input_and_its_channel_axis() -> None:
    """Hand-made graph: a Conv (weight axis 0), a Gemm with and without transB (0 / 1), a
    MatMul whose initializer is input 0 (no channel axis of a weight there: full range
    leaves it alone, 16 bits take it as they take any initializer input) and one whose
    initializer is input 1 (axis 1)."""
    from onnx import helper

    from e3dpsm.quantize.static import full_range_weight_overrides, int16_weight_overrides

    def init(name: str, *shape: int) -> onnx.TensorProto:
        return numpy_helper.from_array(np.ones(shape, np.float32), name)

    nodes = [helper.make_node("Conv", ["x", "wc"], ["c"], name="conv"),
             helper.make_node("Gemm", ["g", "wg"], ["g1"], name="gemm_t", transB=1),
             helper.make_node("Gemm", ["g", "wh"], ["g2"], name="gemm"),
             helper.make_node("MatMul", ["a0", "m"], ["m1"], name="matmul_left"),
             helper.make_node("MatMul", ["m", "wm"], ["m2"], name="matmul")]
    graph = helper.make_graph(nodes, "g", [], [], [init("wc", 4, 2, 3, 3), init("wg", 5, 4), init("wh", 4, 5),
                                                   init("a0", 3, 4), init("wm", 4, 6)])
    model = helper.make_model(graph)
    names = [n.name for n in nodes]
    full = full_range_weight_overrides(model, names, per_channel=True)
    assert full == {"wc": [{"reduce_range": False, "axis": 0}], "wg": [{"reduce_range": False, "axis": 0}],
                    "wh": [{"reduce_range": False, "axis": 1}], "wm": [{"reduce_range": False, "axis": 1}]}
    assert full_range_weight_overrides(model, names, per_channel=False)["wc"] == [{"reduce_range": False}]
    assert full_range_weight_overrides(model, ["conv"], per_channel=True).keys() == {"wc"}
    assert int16_weight_overrides(model, names).keys() == {"wc", "wg", "wh", "a0", "wm"}
