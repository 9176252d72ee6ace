"""Static shapes as profile targets: the static-batch export the profile makes (contract,
parity with the dynamic export and with PyTorch, the tolerance biting at its threshold),
the targets that run it, and the profile's runners split into phases."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from e3dpsm.cli import main
from e3dpsm.errors import ConfigError
from e3dpsm.export.parity import Tolerances, ValueMismatchError
from e3dpsm.profiles.graphs import check_static_graph, graph_metadata, is_static
from e3dpsm.profiles.inputs import moving_edge_frames
from e3dpsm.profiles.targets import GRAPH_HINTS, STATIC_FP32, availability, load_targets
from e3dpsm.runtime.session import StepSession

STATIC_TARGETS = {"ort-cpu-fp32-static", "openvino-cpu-fp32-static", "openvino-cpu-stateful-fp32-static",
                  "openvino-cpu-bf16-static", "openvino-cpu-stateful-bf16-static"}


# -- targets -----------------------------------------------------------------------------
def test_static_targets_load_the_static_graph() -> None:
    targets = load_targets()
    assert STATIC_TARGETS <= set(targets)
    for name in STATIC_TARGETS:
        target = targets[name]
        assert target.static_batch and target.graph == "fp32" and target.graph_key == STATIC_FP32
        dynamic_twin = targets[name.removesuffix("-static")]
        assert (dynamic_twin.runtime, dynamic_twin.precision, dynamic_twin.static_batch) == \
               (target.runtime, target.precision, False)
    status = availability(targets["ort-cpu-fp32-static"], {"fp32": Path("g.onnx"), STATIC_FP32: None}, False)
    assert not status.available and status.reason == GRAPH_HINTS[STATIC_FP32]


def test_static_batch_is_checked_in_a_targets_file(tmp_path: Path) -> None:
    path = tmp_path / "t.toml"
    entry = '[[target]]\nname = "x"\nruntime = "onnxruntime"\nprovider = "CPUExecutionProvider"\nprecision = "int8"\n'
    path.write_text(entry + 'graph = "int8"\nstatic_batch = true\n')
    with pytest.raises(ConfigError, match="static_batch applies to the fp32 graph only"):
        load_targets(path)
    path.write_text(entry + 'graph = "fp32"\nstatic_batch = "yes"\n')
    with pytest.raises(ConfigError, match="static_batch must be true or false"):
        load_targets(path)


# -- the static export ---------------------------------------------------------------------
def test_static_export_contract(tiny_static_graph: Path) -> None:
    graph = onnx.load(str(tiny_static_graph))
    for value in [*graph.graph.input, *graph.graph.output]:
        first = value.type.tensor_type.shape.dim[0]
        assert first.dim_value == 1 and not first.dim_param, value.name
    meta = graph_metadata(tiny_static_graph)
    assert is_static(meta) and meta.config["static_batch"] == 1


def _rollout(path: Path, frames: np.ndarray, window_ms: float) -> list[dict[str, np.ndarray]]:
    session = StepSession(path, threads=1, spin=False)
    state, steps = session.init_state(1), []
    for frame in frames:
        outputs, state = session.step(frame[None], state, window_ms)
        steps.append({**outputs, **state})
    return steps


def test_static_export_matches_the_dynamic_export(tiny_static_graph: Path, tiny_step_graph: Path) -> None:
    """12 carried steps on both graphs: poses within the parity tolerance (0.01 mm), states
    within 1e-4 of their scale, and the rollout actually moves."""
    frames = moving_edge_frames(12, 192, 256, 20.0, seed=2)
    static, dynamic = (_rollout(p, frames.lnes, frames.window_ms) for p in (tiny_static_graph, tiny_step_graph))
    tolerance = Tolerances()
    for got, ref in zip(static, dynamic):
        for name, value in ref.items():
            scale = max(float(np.abs(value).max()), 1e-6)
            limit = tolerance.pose_atol_mm if name.startswith(("pose", "fusion_pose")) else tolerance.state_rtol * scale
            assert float(np.abs(got[name] - value).max()) <= limit, name
    assert float(np.abs(dynamic[-1]["pose"] - dynamic[0]["pose"]).max()) > 1.0  # poses of metre scale move


def _with_pose_offset(path: Path, out: Path, offset_mm: float) -> Path:
    """The graph with `offset_mm` added to its pose output (every joint, every axis)."""
    graph = onnx.load(str(path))
    producer = next(n for n in graph.graph.node if "pose" in n.output)
    producer.output[list(producer.output).index("pose")] = "pose_before_offset"
    for node in graph.graph.node:  # consumers of pose inside the graph keep reading the original
        node.input[:] = ["pose_before_offset" if i == "pose" else i for i in node.input]
    graph.graph.initializer.append(numpy_helper.from_array(np.array(offset_mm, np.float32), "pose_offset"))
    graph.graph.node.append(helper.make_node("Add", ["pose_before_offset", "pose_offset"], ["pose"]))
    onnx.save(graph, str(out))
    return out


def test_static_parity_check_bites_at_its_threshold(tiny_static_graph: Path, tiny_model, tmp_path: Path) -> None:
    """The check the profile runs before timing a static graph: an offset of 0.009 mm on every
    pose passes the 0.01 mm tolerance, 0.011 mm fails it (one clear error)."""
    frames = moving_edge_frames(4, 192, 256, 20.0, seed=3)
    exact = check_static_graph(tiny_model, tiny_static_graph, frames.lnes, frames.window_ms)
    pose = next(d for d in exact.diffs if d.name == "pose")
    assert pose.max_abs < 1e-3 and pose.reference_scale > 100.0  # round-off only, at the scale of real poses
    near = _with_pose_offset(tiny_static_graph, tmp_path / "near.onnx", 0.009)
    assert check_static_graph(tiny_model, near, frames.lnes, frames.window_ms).passed
    over = _with_pose_offset(tiny_static_graph, tmp_path / "over.onnx", 0.011)
    with pytest.raises(ValueMismatchError, match="pose"):
        check_static_graph(tiny_model, over, frames.lnes, frames.window_ms)


# -- the profile command with static targets -------------------------------------------------
def test_profile_exports_and_times_the_static_graph(tmp_path: Path, capsys) -> None:
    out = tmp_path / "prof"
    code = main(["profile", "--variant", "tiny", "--targets", "ort-cpu-fp32,ort-cpu-fp32-static", "--out", str(out),
                 "--steps", "6", "--warmup", "1", "--profile-steps", "3", "--outside-seconds", "1", "--threads", "1"])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert sorted(report["model"]["graphs_exported"]) == ["step_fp32.onnx", "step_fp32_static.onnx"]
    assert is_static(graph_metadata(out / "step_fp32_static.onnx"))
    by_name = {t["name"]: t for t in report["targets"]}
    static = by_name["ort-cpu-fp32-static"]
    assert static["available"] and static["static_batch"] and static["model_bytes"] == (out / "step_fp32_static.onnx").stat().st_size
    p50 = {name: t["latency_ms"]["p50"] for name, t in by_name.items()}
    verdict = report["verdict"]
    assert verdict["fastest"] == min(p50, key=p50.get) and verdict["hz"] == pytest.approx(1e3 / min(p50.values()))
    first_lines = (out / "report.md").read_text().splitlines()[:3]
    assert f"`{verdict['fastest']}`" in first_lines[2] and f"{verdict['hz']:.1f} Hz" in first_lines[2]
    assert static["outside"]["tool"].startswith("onnxruntime") and static["agreement"] > 0
    assert static["runtime_ms"]["p50"] <= static["latency_ms"]["p50"]
    assert "Fastest path on this host" in capsys.readouterr().out


def test_profile_refuses_a_dynamic_graph_as_static_model(tmp_path: Path, tiny_step_graph: Path, capsys) -> None:
    out = tmp_path / "never"
    code = main(["profile", "--model", str(tiny_step_graph), "--static-model", str(tiny_step_graph),
                 "--targets", "ort-cpu-fp32-static", "--out", str(out)])
    assert code == 2 and "has a dynamic batch axis" in capsys.readouterr().err
    assert not out.exists()


# -- the runners' phases -----------------------------------------------------------------------
@pytest.mark.parametrize("runtime", ["onnxruntime", "openvino"])
def test_phased_runner_steps_as_its_session_does(runtime: str, tiny_static_graph: Path) -> None:
    """prepare / run / collect carry the same states as the session's own step."""
    from e3dpsm.profiles.latency import OpenVinoRunner, OrtRunner

    targets = load_targets()
    if runtime == "onnxruntime":
        runner = OrtRunner(str(tiny_static_graph), targets["ort-cpu-fp32-static"], 20.0, side_by_side=True)
        reference = StepSession(tiny_static_graph, threads=1, spin=False)
    else:
        pytest.importorskip("openvino")
        from e3dpsm.runtime.openvino_session import OpenVINOStepSession

        runner = OpenVinoRunner(str(tiny_static_graph), targets["openvino-cpu-fp32-static"], 20.0)
        reference = OpenVINOStepSession(tiny_static_graph, threads=1)
    frames = moving_edge_frames(3, 192, 256, 20.0, seed=5).lnes
    state = reference.init_state(1)
    for frame in frames:
        runner.prepare(frame[None])
        runner.run()
        runner.collect()
        _, state = reference.step(frame[None], state, 20.0)
    for name, value in state.items():
        np.testing.assert_allclose(runner.state[name], value, rtol=1e-5, atol=1e-5, err_msg=name)
    assert float(np.abs(state["fusion_initialised"]).max()) == 1.0  # the fusion ran its update branch
