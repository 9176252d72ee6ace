"""e3dpsm.golden.diagnose on a graph small enough to write out in numpy: three module groups
(`stem`, the recurrent `mem`, `decoder`), one state, and a compressed twin with two Q/DQ pairs.
Every figure of the report (per-step output error, added error, quantisation noise, state
and pose error, growth, the ranking) is checked against the same recurrence in numpy."""
from __future__ import annotations

import math

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from _qdq_reference import qdq_u8
from e3dpsm.errors import DataError
from e3dpsm.golden.diagnose import (GROWTH_RATIO, Series, diagnose, make_plan, markdown, node_groups,
                                    relative_l2)
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.state import StateSpec, state_input_name, state_output_name

STATE = "mem_a"  # family `mem`: a recurrent group
S_IN, S_OUT = state_input_name(STATE), state_output_name(STATE)
X1, POSE = "/stem/Reshape_output_0", "pose"
SCALE = 0.05  # both Q/DQ pairs: u8, zero point 0 (every quantised value is positive)
WINDOW_MS = 50.0  # the decay is window_ms / 100


def _toy(quantised: bool, state_pair: bool = True, decoder_pairs: int = 0,
         rename_stem: bool = False) -> onnx.ModelProto:
    """x1 = reshape(softplus(frame), [batch, -1]) [stem, its shape from unscoped int64 nodes:
    group `other`]; s' = (x1 + s) * window/100 [mem]; pose = softplus(s') [decoder].
    Quantised: x1 and (with `state_pair`) s' pass a Q/DQ pair before their readers (the state
    output stays float); `decoder_pairs` Q/DQ'd multiplications by 1.01 follow the decoder's
    Softplus; `rename_stem` gives the stem's Reshape another name than the reference's."""
    inits = [numpy_helper.from_array(np.array(0.01, np.float32), "hundredth"),
             numpy_helper.from_array(np.array(1.01, np.float32), "gain"),
             numpy_helper.from_array(np.array([0], np.int64), "zero_i"),
             numpy_helper.from_array(np.array([1], np.int64), "one_i"),
             numpy_helper.from_array(np.array([-1], np.int64), "minus_one")]
    if quantised:
        inits += [numpy_helper.from_array(np.array(SCALE, np.float32), "scale"),
                  numpy_helper.from_array(np.array(0, np.uint8), "zero")]
    x1_read, s_read = X1, S_OUT
    nodes = [helper.make_node("Shape", ["lnes"], ["lnes_shape"], name="Shape_0"),
             helper.make_node("Slice", ["lnes_shape", "zero_i", "one_i"], ["batch"], name="Slice_0"),
             helper.make_node("Concat", ["batch", "minus_one"], ["flat_shape"], name="Concat_0", axis=0),
             helper.make_node("Softplus", ["lnes"], ["/stem/Softplus_output_0"], name="/stem/Softplus"),
             helper.make_node("Reshape", ["/stem/Softplus_output_0", "flat_shape"], [X1],
                              name="renamed" if quantised and rename_stem else "/stem/Reshape"),
             helper.make_node("Mul", ["window_ms", "hundredth"], ["decay"], name="/mem/decay")]
    if quantised:
        nodes += [helper.make_node("QuantizeLinear", [X1, "scale", "zero"], ["x1_q"], name="q_x1"),
                  helper.make_node("DequantizeLinear", ["x1_q", "scale", "zero"], ["x1_dq"], name="dq_x1")]
        x1_read = "x1_dq"
    nodes += [helper.make_node("Add", [x1_read, S_IN], ["/mem/sum"], name="/mem/Add"),
              helper.make_node("Mul", ["/mem/sum", "decay"], [S_OUT], name="/mem/Mul")]
    if quantised and state_pair:
        nodes += [helper.make_node("QuantizeLinear", [S_OUT, "scale", "zero"], ["s_q"], name="q_s"),
                  helper.make_node("DequantizeLinear", ["s_q", "scale", "zero"], ["s_dq"], name="dq_s")]
        s_read = "s_dq"
    last = "/decoder/Softplus_output_0" if decoder_pairs else POSE
    nodes.append(helper.make_node("Softplus", [s_read], [last], name="/decoder/Softplus"))
    for k in range(decoder_pairs):
        out = f"/decoder/Mul_{k}_output_0"
        nodes.append(helper.make_node("Mul", [last, "gain"], [out], name=f"/decoder/Mul_{k}"))
        last = POSE if k == decoder_pairs - 1 else f"/decoder/dq_{k}"
        if quantised:
            nodes += [helper.make_node("QuantizeLinear", [out, "scale", "zero"], [f"q{k}"], name=f"q_{k}"),
                      helper.make_node("DequantizeLinear", [f"q{k}", "scale", "zero"], [last], name=f"dq_{k}")]
        else:
            nodes.append(helper.make_node("Identity", [out], [last], name=f"/decoder/Identity_{k}"))
    value = lambda name, shape=(1, 4): helper.make_tensor_value_info(name, TensorProto.FLOAT, list(shape))  # noqa: E731
    graph = helper.make_graph(nodes, "toy", [value("lnes", (1, 1, 2, 2)), value("window_ms", (1,)), value(S_IN)],
                              [value(POSE), value(S_OUT)], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    GraphMetadata(states=(StateSpec(STATE, (4,)),),
                  inputs={"frame": {"name": "lnes", "shape": [1, 1, 2, 2]}, "window": {"name": "window_ms", "shape": [1]}},
                  outputs=[{"name": POSE}], config={"variant": "toy"}, joints=["j"]).write_to(model)
    return model


def _qdq(x: np.ndarray) -> np.ndarray:
    return qdq_u8(x, SCALE, 0)[1]


def _rel(got: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.sum((got.astype(np.float64) - ref) ** 2)) / np.sqrt(np.sum(ref.astype(np.float64) ** 2)))


def _numpy_rollout(frames: np.ndarray) -> dict[str, np.ndarray]:
    """Per-step errors of the toy's two graphs, each carrying its own state."""
    softplus = lambda x: np.log1p(np.exp(x)).astype(np.float32)  # noqa: E731
    decay = np.float32(WINDOW_MS * 0.01)
    s_ref = s_got = np.zeros((1, 4), np.float32)
    rows = []
    for frame in frames:
        x1 = softplus(frame.reshape(1, 4))
        s_ref = (x1 + s_ref) * decay
        x1_dq = _qdq(x1)
        s_got = (x1_dq + s_got) * decay
        s_dq = _qdq(s_got)
        rows.append((_rel(x1_dq, x1), _rel(s_dq, s_ref), _rel(softplus(s_dq), softplus(s_ref)), _rel(s_got, s_ref),
                     _rel(x1_dq, x1), _rel(s_dq, s_got)))
    cols = np.array(rows).T
    return dict(zip(("stem", "mem", "decoder", "state", "noise_stem", "noise_mem"), cols))


@pytest.fixture(scope="module")
def toy_paths(tmp_path_factory):
    folder = tmp_path_factory.mktemp("diagnose_toy")
    reference, model = folder / "reference.onnx", folder / "model.onnx"
    onnx.save(_toy(False), str(reference))
    onnx.save(_toy(True), str(model))
    return reference, model


FRAMES = np.random.default_rng(7).normal(size=(30, 1, 2, 2)).astype(np.float32)  # [C, H, W] each


@pytest.fixture(scope="module")
def toy_result(toy_paths):
    return diagnose(*toy_paths, FRAMES, WINDOW_MS, threads=1)


def test_relative_l2_against_a_loop() -> None:
    rng = np.random.default_rng(0)
    ref, got = rng.normal(size=(3, 5)).astype(np.float32), rng.normal(size=(3, 5)).astype(np.float32)
    num = math.sqrt(sum((float(g) - float(r)) ** 2 for g, r in zip(got.ravel(), ref.ravel())))
    den = math.sqrt(sum(float(r) ** 2 for r in ref.ravel()))
    assert relative_l2(got, ref) == pytest.approx(num / den, rel=1e-12)
    zero = np.zeros(4, np.float32)
    assert relative_l2(zero, zero) == 0.0  # both zero: no error
    assert relative_l2(np.full(4, 1e-3, np.float32), zero) == math.inf  # anything against zero: unbounded
    assert relative_l2(np.full(4, 1e-14), zero.astype(np.float64)) == 0.0  # within TINY of zero counts as zero
    assert relative_l2(np.array([np.nan, 1.0]), np.ones(2)) == math.inf
    assert relative_l2(np.array([np.inf, 1.0]), np.ones(2)) == math.inf


def test_growth_is_the_last_tenth_over_the_second_tenth() -> None:
    errors = np.concatenate([np.full(10, 1.0), np.full(10, 2.0), np.full(20, 3.0), np.full(10, 5.0)])  # 50 steps
    series = Series("g", "group", errors)
    assert series.growth == 5.0  # the median of steps 46-50 over that of steps 6-10
    assert math.isnan(Series("g", "group", np.ones(19)).growth)  # below 20 steps: not measured
    assert Series("g", "group", np.ones(20)).growth == 1.0
    flat_zero = np.zeros(40)
    assert Series("g", "group", flat_zero).growth == 1.0
    rising = np.zeros(40)
    rising[-4:] = 1.0
    assert Series("g", "group", rising).growth == math.inf


def test_to_dict_reports_steps_one_ten_hundred_and_the_last() -> None:
    errors = np.arange(1, 151, dtype=np.float64)  # error k at step k
    entry = Series("s", "state", errors).to_dict()
    assert entry["error_at_step"] == {"1": 1.0, "10": 10.0, "100": 100.0, "150": 150.0}
    assert entry["mean_error"] == pytest.approx(75.5)
    assert entry["growth"] == pytest.approx(np.median(errors[-15:]) / np.median(errors[15:30]))
    assert entry["grows"] is (entry["growth"] > GROWTH_RATIO) is True
    assert "mean_added_error" not in entry and "qdq_noise" not in entry
    short = Series("s", "group", np.array([0.5, 0.25, 0.125]), added=np.array([0.1, 0.2, 0.6]), qdq_noise=0.0).to_dict()
    assert short["error_at_step"] == {"1": 0.5, "3": 0.125}
    assert short["mean_added_error"] == pytest.approx(0.3) and short["qdq_noise"] == 0.0
    assert short["grows"] is False  # NaN growth never grows
    assert Series("s", "state", np.array([1.0] * 10)).to_dict()["error_at_step"] == {"1": 1.0, "10": 1.0}


def test_the_plan_pairs_each_boundary_tensor_with_what_its_readers_read() -> None:
    reference, model = _toy(False), _toy(True)
    meta = GraphMetadata.from_onnx(reference)
    groups = node_groups(reference, meta)
    assert groups == {"/stem/Softplus": "stem", "/stem/Reshape": "stem", "/mem/decay": "mem", "/mem/Add": "mem", "/mem/Mul": "mem",
                      "/decoder/Softplus": "decoder"}
    plan = make_plan(reference, model, meta)
    assert plan.boundary == {X1: "stem", S_OUT: "mem", POSE: "decoder"}  # `/mem/sum` stays inside its group
    assert plan.model_name == {X1: "x1_dq", S_OUT: "s_dq", POSE: POSE}
    assert plan.qdq == {X1: ("x1_dq", "stem"), S_OUT: ("s_dq", "mem")}
    assert plan.states == {STATE: S_OUT}
    assert plan.feeds == {"mem": {"stem"}, "decoder": {"mem"}}
    float_plan = make_plan(reference, reference, meta)
    assert float_plan.model_name == {X1: X1, S_OUT: S_OUT, POSE: POSE} and float_plan.qdq == {}


def test_a_graph_sharing_no_tensor_names_is_refused() -> None:
    reference, model = _toy(False), _toy(True)
    for node in model.graph.node:
        node.output[:] = ["x" + o for o in node.output]
    with pytest.raises(DataError, match=r"^the two graphs share no tensor names; diagnose needs the compressed graph "
                                        r"to come from the reference \(e3dpsm quantize --model REFERENCE\)$"):
        make_plan(reference, model, GraphMetadata.from_onnx(reference))


def test_every_figure_against_the_recurrence_in_numpy(toy_result) -> None:
    expected = _numpy_rollout(FRAMES)
    result = toy_result
    assert (result["steps"], result["window_ms"]) == (30, WINDOW_MS)
    assert (result["matched_tensors"], result["quantised_activations"], result["ranked_by"]) == (3, 2, "qdq_noise")
    groups = {g["name"]: g for g in result["groups"]}
    curves = result["_curves"]["group"]
    for name in ("stem", "mem", "decoder"):
        np.testing.assert_allclose(curves[name], expected[name], rtol=1e-4, atol=1e-7, err_msg=name)
        assert groups[name]["mean_error"] == pytest.approx(np.mean(expected[name]), rel=1e-4)
    added = {"stem": expected["stem"], "mem": np.maximum(expected["mem"] - expected["stem"], 0),
             "decoder": np.maximum(expected["decoder"] - expected["mem"], 0)}
    for name, values in added.items():
        assert groups[name]["mean_added_error"] == pytest.approx(np.mean(values), rel=1e-4, abs=1e-12), name
    assert groups["stem"]["qdq_noise"] == pytest.approx(np.mean(expected["noise_stem"]), rel=1e-4)
    assert groups["mem"]["qdq_noise"] == pytest.approx(np.mean(expected["noise_mem"]), rel=1e-4)
    assert "qdq_noise" not in groups["decoder"]  # no Q/DQ pair of its own
    noisy_first = sorted(("stem", "mem"), key=lambda g: -groups[g]["qdq_noise"])
    assert result["culprits"] == [*noisy_first, "decoder"]
    (state,) = result["states"]
    assert state["name"] == STATE
    np.testing.assert_allclose(result["_curves"]["state"][STATE], expected["state"], rtol=1e-4, atol=1e-7)
    (pose,) = result["outputs"]
    assert pose["name"] == POSE and pose["mean_error"] == pytest.approx(np.mean(expected["decoder"]), rel=1e-4)
    noisiest = result["noisiest_tensors"]
    assert [t["tensor"] for t in noisiest] == [X1 if g == "stem" else S_OUT for g in noisy_first]
    assert [t["group"] for t in noisiest] == noisy_first
    assert noisiest[0]["qdq_noise"] >= noisiest[1]["qdq_noise"] > 0


def test_a_float_graph_ranks_by_added_error(toy_paths, tmp_path) -> None:
    """Without Q/DQ pairs (FP16, dynamic INT8) the culprits are ranked by mean added error;
    here the decoder alone is damaged (its Softplus became a Relu), so it alone adds error."""
    reference, _ = toy_paths
    damaged = _toy(False)
    next(n for n in damaged.graph.node if n.name == "/decoder/Softplus").op_type = "Relu"
    onnx.save(damaged, str(tmp_path / "damaged.onnx"))
    result = diagnose(reference, tmp_path / "damaged.onnx", FRAMES, WINDOW_MS, threads=1)
    assert result["ranked_by"] == "added_error" and result["quantised_activations"] == 0
    assert result["culprits"][0] == "decoder"
    groups = {g["name"]: g for g in result["groups"]}
    assert groups["decoder"]["mean_added_error"] > 0.01
    assert groups["stem"]["mean_added_error"] == groups["mem"]["mean_added_error"] == 0.0
    assert all("qdq_noise" not in g for g in result["groups"]) and result["noisiest_tensors"] == []
    assert result["states"][0]["mean_error"] == 0.0  # the damage is downstream of the state


def test_graphs_with_other_states_or_no_frames_are_refused(toy_paths, tmp_path) -> None:
    reference, model = toy_paths
    other = _toy(True)
    meta = GraphMetadata.from_onnx(other)
    GraphMetadata(states=(StateSpec(STATE, (5,)),), inputs=meta.inputs, outputs=meta.outputs, config=meta.config,
                  joints=meta.joints).write_to(other)
    onnx.save(other, str(tmp_path / "other.onnx"))
    with pytest.raises(DataError, match=r"^\S+other\.onnx and \S+reference\.onnx carry different states; "
                                        r"they are not the same model$"):
        diagnose(reference, tmp_path / "other.onnx", FRAMES, WINDOW_MS)
    with pytest.raises(DataError, match="^no frames to diagnose$"):
        diagnose(reference, model, FRAMES[:0], WINDOW_MS)
    (tmp_path / "damaged.onnx").write_bytes(b"\x08\x07garbage")
    with pytest.raises(DataError, match=r"^\S+damaged\.onnx is not a readable ONNX file: "):
        diagnose(reference, tmp_path / "damaged.onnx", FRAMES, WINDOW_MS)
    with pytest.raises(DataError, match=r"^model \S+absent\.onnx does not exist$"):
        diagnose(tmp_path / "absent.onnx", model, FRAMES, WINDOW_MS)


def test_markdown_lists_every_group_in_rank_order(toy_result) -> None:
    text = markdown(toy_result, "toy")
    lines = text.splitlines()
    assert lines[0] == "# toy" and text.endswith("\n")
    assert "30 steps at 50 ms, both graphs carrying their own states; 3 boundary tensors matched, 2 quantised" in text
    assert "## Culprits (ranked by qdq noise)" in lines
    header = next(line for line in lines if line.startswith("| rank | group |"))
    assert header == "| rank | group | added | step 1 | step 10 | step 30 | QDQ noise | grows |"
    rows = [line for line in lines if line[:4] in ("| 1 ", "| 2 ", "| 3 ")]
    assert [r.split(" | ")[1] for r in rows] == toy_result["culprits"]
    first = toy_result["groups"][0]
    assert rows[0] == (f"| 1 | {first['name']} | {first['mean_added_error']:.2e} | "
                       + " | ".join(f"{first['error_at_step'][m]:.2e}" for m in ("1", "10", "30"))
                       + f" | {first['qdq_noise']:.2e} | {'yes' if first['grows'] else 'no'} (x{first['growth']:.2f}) |")
    assert rows[2].split(" | ")[-2] == "-"  # the decoder has no QDQ noise of its own
    state_row = next(line for line in lines if line.startswith(f"| {STATE} |"))
    assert state_row.count("e-") + state_row.count("e+") == 3
    assert "## Noisiest quantised activations" in lines and f"| `{X1}` | stem |" in text


def test_the_figure_plots_the_top_culprits_and_the_states_with_the_largest_final_error(toy_result, tmp_path,
                                                                                       monkeypatch) -> None:
    import matplotlib.pyplot as plt
    from PIL import Image

    from e3dpsm.golden.diagnose import TINY, diagnosis_figure, plot_diagnosis

    result = dict(toy_result)
    final = {"a": np.array([1.0, 0.1, 0.2]), "b": np.zeros(3), "c": np.array([0.5, 0.3, 0.1])}
    result["_curves"] = {"group": toy_result["_curves"]["group"], "state": final}
    fig = diagnosis_figure(result, top=2)
    try:
        groups, states = fig.axes
        assert [line.get_label() for line in groups.lines] == toy_result["culprits"][:2]
        assert [line.get_label() for line in states.lines] == ["a", "c"]  # by final error, largest first
        first = toy_result["culprits"][0]
        np.testing.assert_array_equal(groups.lines[0].get_ydata(), np.maximum(toy_result["_curves"]["group"][first], TINY))
        assert (groups.get_yscale(), states.get_yscale()) == ("log", "log")
        assert (groups.get_title(), states.get_title()) == ("top culprit groups (output error)", "states")
        assert groups.get_xlabel() == states.get_xlabel() == "step"
        assert groups.get_ylabel() == states.get_ylabel() == "relative L2 error"
        assert [t.get_text() for t in states.get_legend().get_texts()] == ["a", "c"]
        from matplotlib.layout_engine import ConstrainedLayoutEngine

        assert isinstance(fig.get_layout_engine(), ConstrainedLayoutEngine)
        assert states.get_legend().get_texts()[0].get_fontsize() == 7
        assert groups.lines[0].get_linewidth() == 1.0
    finally:
        plt.close(fig)
    zero = dict(result, _curves={"group": result["_curves"]["group"], "state": {"b": np.zeros(3)}})
    fig = diagnosis_figure(zero)
    try:
        assert fig.axes[1].lines[0].get_ydata().tolist() == [TINY] * 3  # zero error still plots on a log axis
    finally:
        plt.close(fig)
    many = dict(result, culprits=[f"g{i}" for i in range(8)],
                _curves={"group": {f"g{i}": np.ones(3) for i in range(8)}, "state": {f"s{i}": np.ones(3) for i in range(8)}})
    fig = diagnosis_figure(many)
    try:
        assert [len(ax.lines) for ax in fig.axes] == [6, 6]  # the top six of each unless asked
    finally:
        plt.close(fig)
    import e3dpsm.golden.diagnose as module

    asked: list[int] = []
    monkeypatch.setattr(module, "diagnosis_figure", lambda result, top: asked.append(top) or diagnosis_figure(result, top))
    plot_diagnosis(toy_result, tmp_path / "d.png")
    assert asked == [6]
    with Image.open(tmp_path / "d.png") as image:
        assert image.size == (1320, 462)  # 12 x 4.2 inches at 110 dpi
    assert plt.get_fignums() == []  # every figure closed


def test_relative_l2_at_the_edge_of_tiny() -> None:
    """Below or at TINY (1e-12) a norm counts as zero, above it divides."""
    assert relative_l2(np.array([2e-12]), np.array([1.5e-12])) == pytest.approx(0.5e-12 / 1.5e-12)
    assert relative_l2(np.array([3e-12]), np.array([1e-12])) == math.inf  # reference norm exactly TINY: zero
    assert relative_l2(np.array([1e-12]), np.array([0.0])) == 0.0  # difference exactly TINY: none
    assert relative_l2(np.array([1.5e-12]), np.array([0.0])) == math.inf


def test_growth_at_the_edges() -> None:
    base = np.full(40, 1e-12)  # early median exactly TINY: counts as zero
    late = base.copy()
    late[-4:] = 5e-12
    assert Series("g", "group", late).growth == math.inf
    assert Series("g", "group", base).growth == 1.0  # TINY late over TINY early: flat
    zero_early = np.zeros(40)
    zero_early[-4:] = 1e-12  # late exactly TINY: flat too
    assert Series("g", "group", zero_early).growth == 1.0
    halfway = np.concatenate([np.ones(30), np.full(10, 2.5)])
    assert Series("g", "group", halfway).to_dict()["grows"] is True  # 2.5 > GROWTH_RATIO (2)
    at_ratio = np.concatenate([np.ones(30), np.full(10, 2.0)])
    entry = Series("g", "group", at_ratio).to_dict()
    assert entry["growth"] == 2.0 and entry["grows"] is False  # growing means above the ratio


def test_plans_are_values() -> None:
    import dataclasses

    reference = _toy(False)
    plan = make_plan(reference, _toy(True), GraphMetadata.from_onnx(reference))
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.states = {}


def test_a_quantised_tensor_whose_producer_was_renamed_keeps_its_reference_group() -> None:
    reference = _toy(False)
    plan = make_plan(reference, _toy(True, rename_stem=True), GraphMetadata.from_onnx(reference))
    assert plan.qdq[X1] == ("x1_dq", "stem")


def test_groups_with_the_same_quantisation_noise_rank_by_added_error(toy_paths, tmp_path) -> None:
    """Only x1 quantised: `mem` and `decoder` have no Q/DQ pair (noise 0) and rank between
    themselves by mean added error, the larger first."""
    reference, _ = toy_paths
    onnx.save(_toy(True, state_pair=False), str(tmp_path / "model.onnx"))
    result = diagnose(reference, tmp_path / "model.onnx", FRAMES, WINDOW_MS, threads=1)
    added = {g["name"]: g["mean_added_error"] for g in result["groups"]}
    assert result["culprits"][0] == "stem"
    assert added["mem"] != added["decoder"]
    assert result["culprits"][1:] == sorted(["mem", "decoder"], key=lambda g: -added[g])
    assert [g["kind"] for g in result["groups"]] == ["group"] * 3
    assert [s["kind"] for s in result["states"]] == ["state"] and [o["kind"] for o in result["outputs"]] == ["output"]


def test_the_ten_noisiest_quantised_activations_are_listed(tmp_path) -> None:
    onnx.save(_toy(False, decoder_pairs=12), str(tmp_path / "reference.onnx"))
    onnx.save(_toy(True, decoder_pairs=12), str(tmp_path / "model.onnx"))
    result = diagnose(tmp_path / "reference.onnx", tmp_path / "model.onnx", FRAMES[:5], WINDOW_MS, threads=1)
    assert result["quantised_activations"] == 14
    noise = [t["qdq_noise"] for t in result["noisiest_tensors"]]
    assert len(noise) == 10 and noise == sorted(noise, reverse=True)


def test_progress_goes_through_tqdm_only_when_asked(toy_paths, monkeypatch) -> None:
    import sys
    import types

    calls: list[dict] = []

    def fake_tqdm(iterable, **kwargs):
        calls.append(kwargs)
        return iter(iterable)

    monkeypatch.setitem(sys.modules, "tqdm", types.SimpleNamespace(tqdm=fake_tqdm))
    quiet = diagnose(*toy_paths, FRAMES[:3], WINDOW_MS, threads=1)
    assert calls == [] and quiet["steps"] == 3
    shown = diagnose(*toy_paths, FRAMES[:3], WINDOW_MS, threads=1, progress=True)
    assert calls == [{"desc": "diagnose", "unit": "step", "leave": False, "disable": None}] and shown["steps"] == 3


def _entry(name: str, errors: dict[str, float], growth: float, **extra) -> dict:
    return {"name": name, "error_at_step": errors, "growth": growth, "grows": growth > GROWTH_RATIO, **extra}


def test_markdown_written_out_whole() -> None:
    result = {
        "steps": 12, "window_ms": 33.3, "matched_tensors": 5, "quantised_activations": 1, "ranked_by": "qdq_noise",
        "groups": [_entry("stem", {"1": 0.001, "10": 0.002, "12": 0.003}, 3.0, mean_added_error=0.0015,
                          qdq_noise=0.01)],
        "states": [_entry("mem_a", {"1": 0.1, "10": 0.2, "12": 0.25}, 1.5)],
        "noisiest_tensors": [{"tensor": "x1", "group": "stem", "qdq_noise": 0.01}],
    }
    assert markdown(result, "toy") == """# toy

12 steps at 33.3 ms, both graphs carrying their own states; 5 boundary tensors matched, 1 quantised activations.

## Culprits (ranked by qdq noise)

| rank | group | added | step 1 | step 10 | step 12 | QDQ noise | grows |
|---:|---|---:|---:|---:|---:|---:|---|
| 1 | stem | 1.50e-03 | 1.00e-03 | 2.00e-03 | 3.00e-03 | 1.00e-02 | yes (x3.00) |

## States

| state | step 1 | step 10 | step 12 | grows |
|---|---:|---:|---:|---|
| mem_a | 1.00e-01 | 2.00e-01 | 2.50e-01 | no (x1.50) |

## Noisiest quantised activations

| tensor | group | QDQ noise |
|---|---|---:|
| `x1` | stem | 1.00e-02 |
"""
    result["groups"][0]["grows"], result["states"][0]["grows"] = False, True
    result["noisiest_tensors"] = []
    text = markdown(result, "toy")
    assert "| 3.00e-03 | 1.00e-02 | no (x3.00) |" in text and "| 2.50e-01 | yes (x1.50) |" in text
    assert text.endswith("| mem_a | 1.00e-01 | 2.00e-01 | 2.50e-01 | yes (x1.50) |\n")
