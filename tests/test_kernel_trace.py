"""The kernel-parity trace (e3dpsm/golden/kernel_cut.py, kernel_trace.py): exposing and cutting
a QDQ graph at its quantised activations, and the exact comparison of codes."""
from __future__ import annotations

import dataclasses

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from _qdq_reference import qdq_u8
from _quantize_helpers import full_integer_dir, quant_data, trained_graph  # noqa: F401
from e3dpsm.golden.kernel_cut import (FEED_SUFFIX, cut_at_quantized, expose_quantized, integer_only,
                                      quantized_activations, segment_ops)
from e3dpsm.golden.kernel_trace import CODE, CodeDiff, compare_codes, first_departures


def _qdq_chain() -> onnx.ModelProto:
    """x -> Q -> DQ -> MatMul (DQ'd s8 weights) -> Q -> DQ -> Sigmoid -> Q -> DQ -> y."""
    rng = np.random.default_rng(0)
    inits = [numpy_helper.from_array(np.array(s, np.float32), n) for n, s in
             (("s_in", 0.05), ("s_mm", 0.2), ("s_sig", 1 / 255), ("s_w", 0.02))]
    inits += [numpy_helper.from_array(np.array(z, np.uint8), n) for n, z in (("z_in", 128), ("z_mm", 128), ("z_sig", 0))]
    inits += [numpy_helper.from_array(rng.integers(-127, 128, (8, 4)).astype(np.int8), "w_q"),
              numpy_helper.from_array(np.array(0, np.int8), "z_w")]
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "s_in", "z_in"], ["x_q"], name="q_in"),
        helper.make_node("DequantizeLinear", ["x_q", "s_in", "z_in"], ["x_dq"], name="dq_in"),
        helper.make_node("DequantizeLinear", ["w_q", "s_w", "z_w"], ["w"], name="dq_w"),
        helper.make_node("MatMul", ["x_dq", "w"], ["mm"], name="matmul"),
        helper.make_node("QuantizeLinear", ["mm", "s_mm", "z_mm"], ["mm_q"], name="q_mm"),
        helper.make_node("DequantizeLinear", ["mm_q", "s_mm", "z_mm"], ["mm_dq"], name="dq_mm"),
        helper.make_node("Sigmoid", ["mm_dq"], ["sig"], name="sigmoid"),
        helper.make_node("QuantizeLinear", ["sig", "s_sig", "z_sig"], ["sig_q"], name="q_sig"),
        helper.make_node("DequantizeLinear", ["sig_q", "s_sig", "z_sig"], ["y"], name="dq_sig"),
    ]
    graph = helper.make_graph(nodes, "chain", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 8])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2, 4])], inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)


def test_quantised_activations_and_their_segments() -> None:
    model = _qdq_chain()
    assert quantized_activations(model) == ["x_q", "mm_q", "sig_q"]  # the weight's codes are a constant
    segments = segment_ops(model)
    assert segments == {"x_q": [], "mm_q": ["MatMul"], "sig_q": ["Sigmoid"]}
    assert [integer_only(segments[q]) for q in ("x_q", "mm_q", "sig_q")] == [False, True, False]


def test_cut_segments_compute_from_the_codes_fed_to_them() -> None:
    """The cut graph fed the exposed graph's own codes reproduces them exactly; a code changed
    upstream moves only the segment that reads it (isolation), and by what numpy says."""
    import onnxruntime as ort

    model = _qdq_chain()
    exposed, names = expose_quantized(model)
    cut, _ = cut_at_quantized(model)
    assert {i.name for i in cut.graph.input} == {"x", *(q + FEED_SUFFIX for q in names)}
    x = np.random.default_rng(1).normal(size=(2, 8)).astype(np.float32)
    run = lambda m, feeds: dict(zip(names, ort.InferenceSession(m.SerializeToString()).run(names, feeds)))  # noqa: E731
    codes = run(exposed, {"x": x})
    feeds = {"x": x, **{q + FEED_SUFFIX: codes[q] for q in names}}
    again = run(cut, feeds)
    assert all(np.array_equal(again[n], codes[n]) for n in names)
    shifted = codes["mm_q"].copy()
    shifted[0, 0] = 255 - shifted[0, 0]  # far enough to move the sigmoid's code
    moved = run(cut, {**feeds, "mm_q" + FEED_SUFFIX: shifted})
    assert np.array_equal(moved["mm_q"], codes["mm_q"]) and np.array_equal(moved["x_q"], codes["x_q"])
    expected = np.clip(np.round(1 / (1 + np.exp(-(shifted[0, 0].astype(np.float32) - 128) * 0.2)) * 255), 0, 255)
    assert moved["sig_q"][0, 0] == expected != codes["sig_q"][0, 0]
    assert np.array_equal(np.delete(moved["sig_q"].ravel(), 0), np.delete(codes["sig_q"].ravel(), 0))


def test_expose_refuses_a_float_graph() -> None:
    model = _qdq_chain()
    float_nodes = [n for n in model.graph.node if n.op_type not in ("QuantizeLinear",)]
    del model.graph.node[:]
    model.graph.node.extend(float_nodes)
    with pytest.raises(ValueError, match="not a QDQ graph"):
        expose_quantized(model)


def _loop_diff(name: str, host: np.ndarray, device: np.ndarray) -> CodeDiff:
    """The comparison written out element by element: the independent reference."""
    first, steps_apart, apart, worst, signed = None, 0, 0, 0, []
    for step in range(host.shape[0]):
        here = 0
        for h, d in zip(host[step].ravel().tolist(), device[step].ravel().tolist()):
            if h != d:
                here += 1
                worst = max(worst, abs(d - h))
                signed.append(d - h)
        if here:
            first = step if first is None else first
            steps_apart += 1
            apart += here
    return CodeDiff(name, first, steps_apart, host[0].size, apart, worst, float(np.mean(signed)) if signed else 0.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compare_codes_matches_an_element_loop(seed: int) -> None:
    rng = np.random.default_rng(seed)
    host = rng.integers(0, 256, (6, 3, 5)).astype(np.uint8)
    device = host.copy()
    for _ in range(4):  # a few codes apart, both ways, including across the u8 ends
        step, i, j = rng.integers(0, 6), rng.integers(0, 3), rng.integers(0, 5)
        device[step, i, j] = np.uint8((int(host[step, i, j]) + int(rng.choice([-3, -1, 1, 2]))) % 256)
    assert compare_codes("t", host, device) == _loop_diff("t", host, device)


def test_compare_codes_counts_wraparound_as_distance_not_modulo() -> None:
    """0 against 255 is 255 codes apart (u8 subtraction would say 1)."""
    host, device = np.zeros((2, 3), np.uint8), np.zeros((2, 3), np.uint8)
    device[1, 2] = 255
    diff = compare_codes("t", host, device)
    assert (diff.first_step, diff.steps_apart, diff.apart, diff.max_codes, diff.mean_signed) == (1, 1, 1, 255, 255.0)
    assert diff.fraction == pytest.approx(1 / 3)
    same = compare_codes("t", host, host)
    assert (same.first_step, same.apart, same.max_codes) == (None, 0, 0)


def test_first_departures_by_step_then_graph_order() -> None:
    diffs = [CodeDiff("a", 5, 1, 4, 1, 1, 1.0), CodeDiff("b", None, 0, 4, 0, 0, 0.0),
             CodeDiff("c", 2, 3, 4, 3, 1, -1.0), CodeDiff("d", 2, 1, 4, 1, 1, 1.0)]
    assert [d.name for d in first_departures(diffs)] == ["c", "d", "a"]
    assert [d.name for d in first_departures(diffs, limit=1)] == ["c"]


def test_golden_check_names_the_activation_where_a_device_departs(tmp_path, trained_graph, quant_data,
                                                                  full_integer_dir) -> None:  # noqa: F811
    """`golden record --kernel-trace` keeps the host's codes; `golden check` whose rollout departs
    from the host's names the activation that departs on its own. A departing device is made
    here by moving the host's records: the poses by 20 mm (question (a) fails) and one code of
    one integer-kernel activation at step 3 by one step (the trace must name exactly it first,
    at step 3, one code apart)."""
    import json

    from e3dpsm.cli import main
    from e3dpsm.golden.kernel_report import HOST_TRACE, ORDER, find_trace
    from e3dpsm.golden.record import sha256_file

    graph = full_integer_dir / "step_int8.onnx"
    golden = tmp_path / "golden"
    assert main(["golden", "record", "--model", str(trained_graph), "--data", str(quant_data), "--steps", "8",
                 "--also", str(graph), "--kernel-trace", "5", "--out", str(golden), "--threads", "1"]) == 0
    folder = find_trace(golden, sha256_file(graph))
    manifest = json.loads((folder / ORDER).read_text())
    target = next(q for q in manifest["codes"][1:] if integer_only(manifest["segments"][q]))
    with np.load(folder / HOST_TRACE) as npz:
        trace = {k: npz[k] for k in npz.files}
    codes = trace[CODE + target]
    codes.reshape(len(codes), -1)[3, 0] ^= 1  # one code one step away at step 3 (in place)
    np.savez_compressed(folder / HOST_TRACE, **trace)
    rollout = next((golden / "host").glob("*.npz"))
    with np.load(rollout) as npz:
        moved = {k: npz[k] + 20.0 for k in npz.files}
    np.savez_compressed(rollout, **moved)
    assert main(["golden", "check", "--model", str(graph), "--golden", str(golden), "--out", str(tmp_path / "chk"),
                 "--exit-zero", "--threads", "1"]) == 0
    report = json.loads((tmp_path / "chk" / "check.json").read_text())
    assert report["questions"]["same_as_host"] is False
    found = report["kernel_trace"]
    assert found["first_departures"][0] == target
    first = found["isolated"][0]
    assert (first["name"], first["first_step"], first["apart"], first["max_codes"]) == (target, 3, 1, 1)


def _recurrent_qdq(path) -> None:
    """A one-state QDQ graph: a = Q(frame + state); h = Q(DQ(a) * 0.5); the new state is DQ(h),
    the pose DQ(h) too. Metadata as the export writes it (one state `s` of shape [4])."""
    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.state import StateSpec, state_input_name, state_output_name

    spec = StateSpec("s", (4,))
    inits = [numpy_helper.from_array(np.array(v, np.float32 if isinstance(v, float) else np.uint8), n) for n, v in
             (("s_a", 0.05), ("z_a", 128), ("s_h", 0.02), ("z_h", 128), ("half", 0.5))]
    nodes = [helper.make_node("Add", ["lnes", state_input_name("s")], ["sum"]),
             helper.make_node("QuantizeLinear", ["sum", "s_a", "z_a"], ["a_q"]),
             helper.make_node("DequantizeLinear", ["a_q", "s_a", "z_a"], ["a"]),
             helper.make_node("Mul", ["a", "half"], ["halved"]),
             helper.make_node("QuantizeLinear", ["halved", "s_h", "z_h"], ["h_q"]),
             helper.make_node("DequantizeLinear", ["h_q", "s_h", "z_h"], [state_output_name("s")]),
             helper.make_node("Identity", [state_output_name("s")], ["pose"])]
    value = lambda name: helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, 4])  # noqa: E731
    graph = helper.make_graph(nodes, "recurrent", [value("lnes"), value(state_input_name("s"))],
                              [value("pose"), value(state_output_name("s"))], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    GraphMetadata(states=(spec,), inputs={"frame": {"name": "lnes", "shape": [1, 4]}, "window": None},
                  outputs=[{"name": "pose"}], config={"variant": "fake"}, joints=["j"]).write_to(model)
    onnx.save(model, str(path))
    return model


def _qdq(value: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(codes, dequantised) with zero point 128, as the toy graphs quantise."""
    return qdq_u8(value, scale, 128)


def test_rollout_carries_the_states_and_keeps_every_code(tmp_path) -> None:
    """The host's trace against the recurrence written out in numpy: inputs (states included)
    as fed, codes and state outputs per step."""
    from e3dpsm.golden.kernel_trace import IN, OUT, rollout
    from e3dpsm.state import state_input_name, state_output_name

    model = _recurrent_qdq(tmp_path / "step.onnx")
    exposed, codes = expose_quantized(model)
    onnx.save(exposed, str(tmp_path / "exposed.onnx"))
    frames = np.random.default_rng(4).normal(size=(5, 1, 4)).astype(np.float32) * 2
    start = np.full((1, 4), 0.3, np.float32)
    inputs = iter([{"lnes": frames[0], state_input_name("s"): start}, *({"lnes": f} for f in frames[1:])])
    trace = rollout(tmp_path / "exposed.onnx", inputs, codes)
    assert codes == ["a_q", "h_q"]
    # the keys are the host.npz format a device reads: written out, not through the constants
    assert set(trace) == {"in.lnes", f"in.{state_input_name('s')}", "q.a_q", "q.h_q", f"out.{state_output_name('s')}"}
    state = start
    for step, frame in enumerate(frames):
        a_codes, a = _qdq(frame + state, 0.05)
        h_codes, h = _qdq(a * np.float32(0.5), 0.02)
        assert np.array_equal(trace[IN + state_input_name("s")][step], state)
        assert np.array_equal(trace[CODE + "a_q"][step], a_codes) and np.array_equal(trace[CODE + "h_q"][step], h_codes)
        assert np.array_equal(trace[OUT + state_output_name("s")][step], h)
        state = h
    assert np.array_equal(trace[IN + "lnes"], frames)
    assert trace[CODE + "a_q"].shape == (5, 1, 4) and trace[CODE + "a_q"].dtype == np.uint8


def test_isolated_segments_compute_from_the_host_codes_alone(tmp_path) -> None:
    """Each step of the cut graph reads the host's codes: h's segment follows a code changed in
    the host's trace (a), not what the device would have computed; a's follows the host's inputs."""
    from e3dpsm.golden.kernel_trace import IN, isolated, load_trace, rollout
    from e3dpsm.state import state_input_name

    model = _recurrent_qdq(tmp_path / "step.onnx")
    exposed, codes = expose_quantized(model)
    onnx.save(exposed, str(tmp_path / "exposed.onnx"))
    onnx.save(cut_at_quantized(model)[0], str(tmp_path / "cut.onnx"))
    frames = np.random.default_rng(5).normal(size=(4, 1, 4)).astype(np.float32)
    inputs = iter([{"lnes": frames[0], state_input_name("s"): np.zeros((1, 4), np.float32)},
                   *({"lnes": f} for f in frames[1:])])
    host = rollout(tmp_path / "exposed.onnx", inputs, codes)
    np.savez(tmp_path / "host.npz", **host)
    host = load_trace(tmp_path / "host.npz")
    host[CODE + "a_q"][2, 0, 1] = 250  # the host's trace says otherwise at step 2
    host[IN + "not_an_input"] = np.zeros((4, 1), np.float32)  # a trace may keep inputs the cut graph lacks
    cut_inputs = {i.name for i in onnx.load(str(tmp_path / "cut.onnx")).graph.input}
    assert cut_inputs == {"lnes", state_input_name("s"), "a_q__host_codes", "h_q__host_codes"}
    got = isolated(tmp_path / "cut.onnx", host, codes)
    assert set(got) == {CODE + "a_q", CODE + "h_q"}
    for step in range(4):
        a_codes, _ = _qdq(host[IN + "lnes"][step] + host[IN + state_input_name("s")][step], 0.05)
        fed = (host[CODE + "a_q"][step].astype(np.float32) - 128) * np.float32(0.05)
        h_codes, _ = _qdq(fed * np.float32(0.5), 0.02)
        assert np.array_equal(got[CODE + "a_q"][step], a_codes)
        assert np.array_equal(got[CODE + "h_q"][step], h_codes)
    assert got[CODE + "h_q"][2, 0, 1] == _qdq(np.float32(122 * 0.05 * 0.5), 0.02)[0]


def test_code_diff_dict_and_fraction_of_the_steps_apart() -> None:
    """The fraction counts the codes apart over the codes of the steps that part (not of every
    step); a rollout that never parts has fraction 0, not a division by zero."""
    host = np.zeros((5, 4), np.uint8)
    device = host.copy()
    device[1, :3] = 2
    device[3, 0] = 1
    diff = compare_codes("t", host, device)
    assert diff.fraction == pytest.approx(4 / (4 * 2))
    assert diff.to_dict() == {"name": "t", "first_step": 1, "steps_apart": 2, "elements": 4, "apart": 4,
                              "max_codes": 2, "mean_signed": 1.75, "fraction_of_apart_steps": 0.5}
    same = compare_codes("t", host, host)
    assert (same.fraction, same.mean_signed) == (0.0, 0.0)
    one_step = compare_codes("t", host[1:2], device[1:2])
    assert (one_step.elements, one_step.apart, one_step.first_step) == (4, 3, 0)
    with pytest.raises(dataclasses.FrozenInstanceError):  # a value, as reports hold it
        diff.apart = 0


def test_traces_compare_in_the_given_order_and_refuse_other_shapes() -> None:
    from e3dpsm.golden.kernel_trace import compare_traces

    host = {CODE + "a": np.zeros((2, 3), np.uint8), CODE + "b": np.ones((2, 2), np.uint8)}
    device = {CODE + "a": np.zeros((2, 3), np.uint8), CODE + "b": np.full((2, 2), 3, np.uint8)}
    diffs = compare_traces(host, device, ["b", "a"])
    assert [(d.name, d.apart, d.max_codes) for d in diffs] == [("b", 4, 2), ("a", 0, 0)]
    with pytest.raises(ValueError, match=r"^a: host codes \(2, 3\), device codes \(2, 4\)$"):
        compare_codes("a", host[CODE + "a"], np.zeros((2, 4), np.uint8))


def test_first_departures_are_five_unless_asked() -> None:
    diffs = [CodeDiff(f"c{i}", 10 - i, 1, 4, 1, 1, 1.0) for i in range(8)]
    assert [d.name for d in first_departures(diffs)] == ["c7", "c6", "c5", "c4", "c3"]


def test_a_trace_with_pickled_objects_is_refused(tmp_path) -> None:
    """host.npz comes with a golden from another machine: numpy arrays only, no pickles."""
    from e3dpsm.golden.kernel_trace import load_trace

    np.savez(tmp_path / "host.npz", **{"q.a": np.array([{"x": 1}], dtype=object)})
    with pytest.raises(ValueError, match="allow_pickle"):
        load_trace(tmp_path / "host.npz")


def test_a_single_value_fraction_of_code_steps() -> None:
    """One code over three steps, apart at one: every code of the step that parts."""
    host = np.zeros((3, 1), np.uint8)
    device = host.copy()
    device[1, 0] = 1
    assert compare_codes("t", host, device).fraction == 1.0


def test_a_trace_without_steps_is_refused_in_one_line(tmp_path, capsys) -> None:
    """A zero-step trace has nothing to compare: `--steps 0` is refused before anything is
    written, a manifest that says 0 steps before its trace is read, and the comparison itself
    names the activation instead of failing inside numpy."""
    from e3dpsm.golden.kernel_report import ORDER, main

    with pytest.raises(ValueError, match=r"^a: no steps to compare \(codes of shape \(0, 3\)\)$"):
        compare_codes("a", np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.uint8))
    with pytest.raises(ValueError, match=r"^a: no steps to compare \(codes of shape \(\)\)$"):
        compare_codes("a", np.array(3, np.uint8), np.array(3, np.uint8))
    one_code = compare_codes("a", np.array([1, 2, 3], np.uint8), np.array([1, 4, 3], np.uint8))  # one code a step
    assert (one_code.first_step, one_code.apart, one_code.max_codes) == (1, 1, 2)
    _recurrent_qdq(tmp_path / "step.onnx")
    out = tmp_path / "trace"
    assert main(["host", str(tmp_path / "step.onnx"), str(tmp_path / "golden"), str(out), "--steps", "0"]) == 2
    err = capsys.readouterr().err
    assert err == "python -m e3dpsm.golden.kernel_report host: error: --steps must be at least 1, got 0\n"
    assert not out.exists()
    out.mkdir()
    (out / ORDER).write_text('{"graph": "g.onnx", "codes": ["a_q"], "segments": {"a_q": []}, "steps": 0}')
    assert main(["device", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the host trace holds no steps (0); record it again" in err
    assert [p.name for p in out.iterdir()] == [ORDER]
