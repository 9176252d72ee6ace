"""Which graph OpenVINO executes: the heavy layers of a compiled model by run-time precision
(`runtime.openvino_session.executed_layers`), on the trained tiny's INT8 graph. Why the
profile's benchmark_app compiles the file as it is (`-lfile`): a PrePostProcessor built on
the INT8 graph, as benchmark_app otherwise does, leaves its convolutions in f32."""
from __future__ import annotations

from pathlib import Path

import pytest

from _quantize_helpers import full_integer_dir, quant_data, trained_graph  # noqa: F401

ov = pytest.importorskip("openvino")

from e3dpsm.profiles.outside import exec_graph_layers  # noqa: E402
from e3dpsm.runtime.openvino_session import compile_config, executed_layers, read_openvino_model  # noqa: E402


def _compiled(graph: Path, prepostprocessor: bool = False, unprotected: bool = False):
    """`graph` compiled as e3dpsm reads it, or (`unprotected`) read by OpenVINO's read_model
    alone; behind a PrePostProcessor built with nothing asked of it where asked."""
    core, model = read_openvino_model(graph)
    if unprotected:
        model = core.read_model(str(graph))
    if prepostprocessor:
        from openvino.preprocess import PrePostProcessor

        model = PrePostProcessor(model).build()
    return core.compile_model(model, "CPU", compile_config(1))


def test_executed_layers_read_as_the_serialised_executed_graph(full_integer_dir, tmp_path) -> None:  # noqa: F811
    """The compiled model's run-time graph counted from its ops' rt_info, and the same graph
    serialised to XML (the form benchmark_app's -exec_graph_path writes) and read back by
    the profile's reader: one count. The INT8 graph runs its convolutions in u8."""
    compiled = _compiled(full_integer_dir / "step_int8.onnx")
    counts = executed_layers(compiled)
    ov.serialize(compiled.get_runtime_model(), str(tmp_path / "exec.xml"), str(tmp_path / "exec.bin"))
    assert exec_graph_layers(tmp_path / "exec.xml") == counts
    assert counts.get("Convolution u8", 0) >= 20 and "Convolution f32" not in counts


def test_a_prepostprocessor_leaves_the_int8_convolutions_in_f32(full_integer_dir) -> None:  # noqa: F811
    """OpenVINO 2026.4, the graph read by `read_model` alone: PrePostProcessor.build() with
    nothing asked of it constant-folds parts of the QDQ graph's dequantisation, and the CPU
    plugin then runs every convolution in f32 (docs/runtimes.md). If a release stops doing
    so, this fails: `protect_dequantization` and benchmark_app's -lfile may go."""
    graph = full_integer_dir / "step_int8.onnx"
    direct = executed_layers(_compiled(graph, unprotected=True))
    built = executed_layers(_compiled(graph, prepostprocessor=True, unprotected=True))
    convolutions = sum(count for name, count in direct.items() if name.startswith("Convolution "))
    assert direct["Convolution u8"] == convolutions
    assert built.get("Convolution u8", 0) == 0 and built["Convolution f32"] == convolutions


@pytest.mark.slow  # ~15 s: a fresh interpreter compiles the graph and steps it for 1 s
def test_benchmark_app_executes_the_graph_the_runner_compiles(full_integer_dir, tmp_path) -> None:  # noqa: F811
    """The INT8 target's outside figure comes from the graph the profile's runner runs (heavy
    layers by run-time precision equal), so the two are compared."""
    from e3dpsm.profiles.agreement import executed_mismatch, outside_timer
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.latency import OpenVinoRunner
    from e3dpsm.profiles.targets import load_targets

    target = load_targets()["openvino-cpu-int8"]
    graph = full_integer_dir / "step_int8.onnx"
    frames = moving_edge_frames(1, 192, 256, 20.0)
    timer = outside_timer(target, graph, frames, 1, tmp_path, profiler_steps=0, turns=1)
    assert timer.turn(0) is None
    figure = timer.figure()
    runner = OpenVinoRunner(str(graph), target, frames.window_ms)
    assert figure.executed == executed_layers(runner.compiled) and figure.executed.get("Convolution u8", 0) >= 20
    assert executed_mismatch(runner, figure) is None


def test_the_ir_keeps_the_int8_convolutions_through_a_fixed_batch_and_a_prepostprocessor(
        full_integer_dir, tmp_path) -> None:  # noqa: F811
    """`e3dpsm convert openvino` protects the INT8 graph's dequantisation (as OpenVINO's own
    converter does): the stateful IR (its batch fixed at 1) and the dynamic IR compiled
    behind an application's PrePostProcessor both run every convolution the ONNX graph runs
    in u8 in u8."""
    from e3dpsm.cli import main
    from e3dpsm.runtime.openvino_stateful import OpenVINOStatefulSession

    graph = full_integer_dir / "step_int8.onnx"
    direct = executed_layers(_compiled(graph))
    assert main(["convert", "openvino", "--model", str(graph), "--out", str(tmp_path / "stateful"), "--stateful"]) == 0
    stateful = executed_layers(OpenVINOStatefulSession(tmp_path / "stateful" / "step_int8.xml", threads=1).compiled)
    assert stateful["Convolution u8"] == direct["Convolution u8"] and "Convolution f32" not in stateful
    assert main(["convert", "openvino", "--model", str(graph), "--out", str(tmp_path / "dynamic")]) == 0
    built = executed_layers(_compiled(tmp_path / "dynamic" / "step_int8.xml", prepostprocessor=True))
    assert built["Convolution u8"] == direct["Convolution u8"] and "Convolution f32" not in built
