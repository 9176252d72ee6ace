"""The outside tools' runs (profiles/outside.py) with the tools faked at the subprocess: what
benchmark_app and onnxruntime_perf_test are given (command, files, time bound), what comes
back from their reports, and each way a run fails as one line. `_run` itself on tiny
Python commands."""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import e3dpsm.profiles.outside as outside
from e3dpsm.profiles.outside import (BENCHMARK_APP, PERF_TEST, OutsideFigure, _run, perf_test_args,
                                     run_benchmark_app, run_perf_test)

SAMPLES = Path(__file__).parent / "fixtures" / "outside_tools"
BENCHMARK_MAIN = "import sys; from openvino.tools.benchmark.main import main; sys.exit(main())"


class FakeTool:
    """Stands in for `_run`: records each call and, as the tool would, writes its files
    (benchmark_app: the report in -report_folder, the executed graph at -exec_graph_path;
    onnxruntime_perf_test: its output in the log)."""

    def __init__(self, failure: str | None = None, report: dict | None = None, exec_graph: str | None = None,
                 output: str = "") -> None:
        self.failure, self.report, self.exec_graph, self.output = failure, report, exec_graph, output
        self.calls: list[tuple[list[str], float, Path]] = []

    def __call__(self, command: list[str], timeout_s: float, log: Path) -> str | None:
        self.calls.append((command, timeout_s, log))
        log.write_text(self.output)
        flag = {command[i]: command[i + 1] for i in range(len(command) - 1)}
        if self.report is not None:
            Path(flag["-report_folder"], "benchmark_report.json").write_text(json.dumps(self.report))
        if self.exec_graph is not None:
            Path(flag["-exec_graph_path"]).write_text(self.exec_graph)
        return self.failure


REPORT = {"execution_results": {"latency (ms)": "12.5", "total number of iterations": "80"}}


@pytest.fixture()
def benchmark_app(monkeypatch):
    monkeypatch.setattr(outside, "benchmark_app_available", lambda: True)

    def install(tool: FakeTool) -> FakeTool:
        monkeypatch.setattr(outside, "_run", tool)
        return tool
    return install


@pytest.mark.parametrize("dynamic", [True, False])
def test_benchmark_app_gets_its_inputs_as_files_and_its_figure_read_back(benchmark_app, tmp_path, dynamic) -> None:
    tool = benchmark_app(FakeTool(report=REPORT, exec_graph=(SAMPLES / "exec_graph.xml").read_text()))
    lnes = np.arange(2 * 3, dtype=np.float32).reshape(1, 2, 3)
    state = np.full((1, 4), 0.5, np.float32)
    work = tmp_path / "turn0"  # made by the run
    figure = run_benchmark_app(Path("m.xml"), {"INFERENCE_NUM_THREADS": 2}, 7.0, work,
                               {"lnes": lnes, "s5/re:in": state}, dynamic)
    (command, timeout_s, log), = tool.calls
    assert command[:3] == [sys.executable, "-c", BENCHMARK_MAIN]
    args = command[3:]
    assert args == outside.benchmark_app_args(Path("m.xml"), {"INFERENCE_NUM_THREADS": 2}, 7.0, work,
                                              {"lnes": work / "lnes.npy", "s5/re:in": work / "s5_re_in.npy"},
                                              {"lnes": (1, 2, 3), "s5/re:in": (1, 4)} if dynamic else None,
                                              work / "config.json")
    assert timeout_s == 7.0 + 300 and log == work / "benchmark_app.log"
    np.testing.assert_array_equal(np.load(work / "lnes.npy"), lnes)
    np.testing.assert_array_equal(np.load(work / "s5_re_in.npy"), state)
    assert figure == OutsideFigure(BENCHMARK_APP, 12.5, 80, " ".join(["benchmark_app", *args]),
                                   executed={"Convolution f32": 1, "Convolution u8": 2, "FullyConnected f32": 1,
                                             "FullyConnected u8": 1})


def test_benchmark_app_failures_are_one_line_each(benchmark_app, monkeypatch, tmp_path) -> None:
    inputs = {"lnes": np.zeros((1, 2), np.float32)}
    graph = (SAMPLES / "exec_graph.xml").read_text()
    benchmark_app(FakeTool(failure="exit 1: [ ERROR ] boom"))
    failed = run_benchmark_app(Path("m.xml"), {}, 1.0, tmp_path / "a", inputs, False)
    assert failed.reason == "exit 1: [ ERROR ] boom" and failed.command.startswith("benchmark_app -m m.xml -lfile")
    assert failed.p50_ms is None
    benchmark_app(FakeTool(report=None, exec_graph=graph))
    missing = run_benchmark_app(Path("m.xml"), {}, 1.0, tmp_path / "b", inputs, False)
    assert missing.reason.startswith("unreadable report: [Errno 2] No such file or directory")
    assert "benchmark_report.json" in missing.reason and missing.command.startswith("benchmark_app ")
    benchmark_app(FakeTool(report={"execution_results": {}}, exec_graph=graph))
    assert run_benchmark_app(Path("m.xml"), {}, 1.0, tmp_path / "c", inputs, False).reason.startswith(
        "unreadable report: benchmark_app report lacks its median latency")
    benchmark_app(FakeTool(report=REPORT, exec_graph="<net><layers>"))
    assert run_benchmark_app(Path("m.xml"), {}, 1.0, tmp_path / "d", inputs, False).reason.startswith(
        "unreadable report: no element found")
    benchmark_app(FakeTool(report=REPORT))  # the executed graph not written
    assert "exec_graph.xml" in run_benchmark_app(Path("m.xml"), {}, 1.0, tmp_path / "e", inputs, False).reason
    monkeypatch.setattr(outside, "benchmark_app_available", lambda: False)
    assert run_benchmark_app(Path("m.xml"), {}, 1.0, tmp_path / "f", inputs, False) == OutsideFigure(
        BENCHMARK_APP, reason="openvino.tools.benchmark is not installed (pip install openvino)")
    assert not (tmp_path / "f").exists()


def test_perf_test_runs_the_tool_on_path_and_reads_its_median(monkeypatch, tmp_path) -> None:
    tool = FakeTool(output=(SAMPLES / "onnxruntime_perf_test.txt").read_text())
    monkeypatch.setattr(outside, "_run", tool)
    monkeypatch.setattr(outside, "perf_test_path", lambda: "/opt/ort/onnxruntime_perf_test")
    figure = run_perf_test(Path("g.onnx"), 2, 4.4, True, tmp_path / "w")
    (command, timeout_s, log), = tool.calls
    args = perf_test_args(Path("g.onnx"), 2, 4.4, True)
    assert command == ["/opt/ort/onnxruntime_perf_test", *args] and timeout_s == 4.4 + 300
    assert log == tmp_path / "w" / "perf_test.log"
    assert figure == OutsideFigure(PERF_TEST, pytest.approx(20.1223), 243, " ".join([PERF_TEST, *args]))
    monkeypatch.setattr(outside, "_run", FakeTool(failure="timed out after 304 s"))
    assert run_perf_test(Path("g.onnx"), 2, 4.4, False, tmp_path / "x").reason == "timed out after 304 s"
    monkeypatch.setattr(outside, "_run", FakeTool(output="Total inference requests: 3\n"))
    silent = run_perf_test(Path("g.onnx"), 2, 4.4, False, tmp_path / "y")
    assert silent.reason == "onnxruntime_perf_test printed no 'P50 Latency' line (was -s given?)"
    assert silent.command == " ".join([PERF_TEST, *perf_test_args(Path("g.onnx"), 2, 4.4, False)])
    monkeypatch.setattr(outside, "perf_test_path", lambda: None)
    assert run_perf_test(Path("g.onnx"), 2, 4.4, False, tmp_path / "z") == OutsideFigure(
        PERF_TEST, reason="onnxruntime_perf_test is not on PATH (not in the onnxruntime wheel)")


def test_perf_test_arguments_whole() -> None:
    assert perf_test_args(Path("g.onnx"), 3, 0.2, dynamic=True) == [
        "-m", "duration", "-t", "1", "-e", "cpu", "-x", "3", "-y", "1", "-I", "-s", "-f", "batch:1", "g.onnx"]
    assert perf_test_args(Path("g.onnx"), 1, 6.6, dynamic=False)[:4] == ["-m", "duration", "-t", "7"]


def test_perf_test_path_is_the_tool_on_path(monkeypatch, tmp_path) -> None:
    tool = tmp_path / PERF_TEST
    tool.write_text("#!/bin/sh\n")
    tool.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    assert outside.perf_test_path() == shutil.which(PERF_TEST) == str(tool)


def test_a_tools_failure_line_is_its_last_error_or_last_line(tmp_path) -> None:
    script = ("print('[ INFO ] reading'); print('[ ERROR ] first'); print('Exception: second'); "
              "print('done'); print('   '); raise SystemExit(4)")
    assert _run([sys.executable, "-c", script], 60, tmp_path / "a.txt") == "exit 4: Exception: second"
    assert _run([sys.executable, "-c", "print('  last words  '); raise SystemExit(2)"], 60,
                tmp_path / "b.txt") == "exit 2: last words"
    assert _run([sys.executable, "-c", "raise SystemExit(5)"], 60, tmp_path / "c.txt") == "exit 5: no output"
    long = _run([sys.executable, "-c", "print('error ' + 'x' * 400); raise SystemExit(1)"], 60, tmp_path / "d.txt")
    assert long == "exit 1: error " + "x" * 294
    assert (tmp_path / "a.txt").read_text().splitlines()[0] == "[ INFO ] reading"  # the output kept in the log
    assert _run([sys.executable, "-c", "import time; time.sleep(30)"], 0.6, tmp_path / "e.txt") == "timed out after 1 s"
    assert _run([str(tmp_path / "none")], 60, tmp_path / "f.txt") == "could not start: No such file or directory"


def test_benchmark_app_arguments_whole(tmp_path) -> None:
    """The exact command line for a static graph with a property no flag carries (the list
    docs/validate-and-profile.md describes); a fraction of a second still runs one."""
    config = {"INFERENCE_NUM_THREADS": 3, "NUM_STREAMS": 1, "PERFORMANCE_HINT": "LATENCY",
              "INFERENCE_PRECISION_HINT": "f32", "DYNAMIC_QUANTIZATION_GROUP_SIZE": 0}
    args = outside.benchmark_app_args(Path("m.xml"), config, 0.4, tmp_path, {"lnes": tmp_path / "l.npy"}, None,
                                      tmp_path / "config.json")
    assert args == ["-m", "m.xml", "-lfile", "-d", "CPU", "-hint", "none", "-nstreams", "1", "-api", "sync",
                    "-infer_precision", "f32", "-t", "1", "-inference_only", "true", "-json_stats", "-report_type",
                    "no_counters", "-report_folder", str(tmp_path), "-exec_graph_path", str(tmp_path / "exec_graph.xml"),
                    "-i", f"lnes:{tmp_path / 'l.npy'}", "-nthreads", "3", "-load_config", str(tmp_path / "config.json")]
    # the flags' properties stay out of -load_config (benchmark_app sets them from its flags)
    assert json.loads((tmp_path / "config.json").read_text()) == {"CPU": {"DYNAMIC_QUANTIZATION_GROUP_SIZE": 0}}


def test_run_benchmark_app_makes_nested_folders_reuses_one_and_names_its_config_file(benchmark_app, tmp_path) -> None:
    tool = benchmark_app(FakeTool(report=REPORT, exec_graph=(SAMPLES / "exec_graph.xml").read_text()))
    work = tmp_path / "a" / "b" / "turn0"
    config = {"DYNAMIC_QUANTIZATION_GROUP_SIZE": 0}
    for _ in range(2):  # a folder that exists is used as it is
        assert run_benchmark_app(Path("m.xml"), config, 1.0, work, {"lnes": np.zeros((1, 2), np.float32)},
                                 False).reason is None
    args = tool.calls[-1][0]
    assert args[args.index("-load_config") + 1] == str(work / "config.json")
    assert json.loads((work / "config.json").read_text()) == {"CPU": config}


def test_a_long_unreadable_report_is_cut_to_300_characters(benchmark_app, tmp_path) -> None:
    benchmark_app(FakeTool(report={"execution_results": {f"key{i}": i for i in range(100)}},
                           exec_graph=(SAMPLES / "exec_graph.xml").read_text()))
    figure = run_benchmark_app(Path("m.xml"), {}, 1.0, tmp_path, {"lnes": np.zeros((1, 2), np.float32)}, False)
    text = ("benchmark_app report lacks its median latency or iteration count (KeyError('latency (ms)')); "
            f"execution_results: { {f'key{i}': i for i in range(100)} }")
    assert figure.reason == "unreadable report: " + text[:300]


def test_the_executed_graph_counts_a_layer_without_a_precision_as_unknown(tmp_path) -> None:
    (tmp_path / "g.xml").write_text(
        '<net><layers><layer id="0" type="Convolution"/><layer id="1" type="MatMul"><data shape="1"/></layer>'
        '<layer id="2"><data runtimePrecision="u8"/></layer>'
        '<layer id="3" type="FullyConnected"><data runtimePrecision="i8"/></layer></layers></net>')
    assert outside.exec_graph_layers(tmp_path / "g.xml") == {"Convolution ?": 1, "FullyConnected i8": 1,
                                                             "MatMul ?": 1}


def test_heavy_layers_are_the_four_kinds_that_carry_the_arithmetic() -> None:
    from e3dpsm.runtime.openvino_session import count_heavy_layers

    pairs = [("Convolution", "u8"), ("Deconvolution", "f32"), ("FullyConnected", "i8"), ("MatMul", "bf16"),
             ("Convolution", "u8"), ("Eltwise", "f32"), ("Reorder", "u8"), (None, "f32"), ("Pooling", "u8")]
    assert count_heavy_layers(pairs) == {"Convolution u8": 2, "Deconvolution f32": 1, "FullyConnected i8": 1,
                                         "MatMul bf16": 1}
    assert list(count_heavy_layers([("MatMul", "f32"), ("Convolution", "u8")])) == ["Convolution u8", "MatMul f32"]


def test_outside_figures_default_to_nothing_and_are_immutable() -> None:
    import dataclasses

    figure = OutsideFigure("benchmark_app")
    assert figure.to_dict() == {"tool": "benchmark_app", "p50_ms": None, "runs": None, "command": None, "reason": None,
                                "round_p50_ms": None, "note": None, "executed": None}
    with pytest.raises(dataclasses.FrozenInstanceError):
        figure.p50_ms = 1.0
    assert outside.ORT_PROFILER == "onnxruntime profiler (model_run)"  # the name the report prints


def test_benchmark_app_is_found_where_openvino_is_installed() -> None:
    import importlib.util

    assert outside.benchmark_app_available() is (importlib.util.find_spec("openvino") is not None)


def test_undecodable_tool_output_is_read_with_replacement_characters(monkeypatch, tmp_path) -> None:
    bad = b"\xff\xfe noise\n"
    script = f"import sys; sys.stdout.buffer.write({bad!r} + b'[ ERROR ] \\xff broken\\nlast line\\n'); sys.exit(1)"
    assert _run([sys.executable, "-c", script], 60, tmp_path / "a.txt") == "exit 1: [ ERROR ] \ufffd broken"

    class BytesTool(FakeTool):
        def __call__(self, command, timeout_s, log):
            self.calls.append((command, timeout_s, log))
            log.write_bytes(bad + (SAMPLES / "onnxruntime_perf_test.txt").read_bytes())
            return None

    monkeypatch.setattr(outside, "_run", BytesTool())
    monkeypatch.setattr(outside, "perf_test_path", lambda: "perf_test")
    assert run_perf_test(Path("g.onnx"), 1, 1.0, False, tmp_path / "a" / "b").p50_ms == pytest.approx(20.1223)
    assert run_perf_test(Path("g.onnx"), 1, 1.0, False, tmp_path / "a" / "b").runs == 243  # the folder reused
