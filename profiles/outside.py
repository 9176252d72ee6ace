"""The runtimes' own timers, run on the graph and settings a profile target uses, so the
profile's figures can be checked against them:

- OpenVINO: `benchmark_app` (shipped in the `openvino` wheel as
  `openvino.tools.benchmark.main`), run as a subprocess of this interpreter with one stream,
  synchronous requests, the target's thread count and inference precision and the rest of
  its compile properties, on the target's graph converted to an IR (stateful targets: the
  stateful IR), fed the profile's first frame, window length and initial states. Its median
  covers `infer()` alone, inputs set once (`-inference_only`), as the profile's runtime
  phase does. It compiles the file as it is (`-lfile`): without it benchmark_app builds a
  PrePostProcessor on the model first, which constant-folds parts of an INT8 QDQ graph's
  dequantisation, and OpenVINO then runs that graph's convolutions in f32 (`small`: 0 of 37
  in u8; benchmark_app's median 12.7 against the runner's 9.5 ms, OpenVINO 2026.4). Each
  run writes its executed graph (`-exec_graph_path`); its heavy layers by run-time
  precision (`executed`) are compared with the runner's compiled model (profiles.agreement).
- ONNX Runtime: `onnxruntime_perf_test` where it is on PATH (it is not in the pip wheel),
  else ONNX Runtime's own profiler: the median `model_run` event of a profiled session
  (`profiles.ort_profile.summarize_trace`).
"""
from __future__ import annotations

import importlib.util
import json
import re
import shutil
import subprocess
import sys
from xml.etree import ElementTree
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

BENCHMARK_APP = "benchmark_app"
PERF_TEST = "onnxruntime_perf_test"
ORT_PROFILER = "onnxruntime profiler (model_run)"
# Properties benchmark_app sets from its own flags; every other compile property of the
# target goes to it through -load_config.
_FLAG_PROPERTIES = ("PERFORMANCE_HINT", "NUM_STREAMS", "INFERENCE_NUM_THREADS", "INFERENCE_PRECISION_HINT")
DEFAULT_TURNS = 3  # turns an outside timer and the target's runner take (profiles.agreement)
EXEC_GRAPH = "exec_graph.xml"  # benchmark_app's executed graph, in its report folder
UNKNOWN_PRECISION = "?"  # a layer of the executed graph that names no run-time precision
_START_UP_SECONDS = 300  # reading and compiling `paper` on a loaded 2-core host, with margin


@dataclass(frozen=True)
class OutsideFigure:
    """An outside tool's median for one target, or why there is none."""

    tool: str
    p50_ms: float | None = None
    runs: int | None = None
    command: str | None = None
    reason: str | None = None
    round_p50_ms: tuple[float, ...] | None = None  # one median per turn (profiles.agreement)
    note: str | None = None
    executed: dict[str, int] | None = None  # the tool's executed graph (count_heavy_layers)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class OutsideToolError(RuntimeError):
    """The tool ran but its output could not be read."""


# -- benchmark_app -------------------------------------------------------------------------
def benchmark_app_available() -> bool:
    return importlib.util.find_spec("openvino.tools.benchmark.main") is not None


def benchmark_app_args(model: Path, config: Mapping[str, Any], seconds: float, report_folder: Path,
                       inputs: Mapping[str, Path], data_shapes: Mapping[str, Sequence[int]] | None,
                       config_file: Path) -> list[str]:
    """benchmark_app's arguments for a model compiled with `config` (as
    `runtime.openvino_session.compile_config` makes it); `data_shapes` for a graph with a
    dynamic batch (kept dynamic, as the profile runs it; -shape would make it static)."""
    precision = str(config.get("INFERENCE_PRECISION_HINT", "f32"))
    args = ["-m", str(model), "-lfile", "-d", "CPU", "-hint", "none", "-nstreams", "1", "-api", "sync",
            "-infer_precision", precision, "-t", str(max(1, round(seconds))), "-inference_only", "true",
            "-json_stats", "-report_type", "no_counters", "-report_folder", str(report_folder),
            "-exec_graph_path", str(report_folder / EXEC_GRAPH),
            "-i", ",".join(f"{name}:{path}" for name, path in inputs.items())]
    if config.get("INFERENCE_NUM_THREADS"):
        args += ["-nthreads", str(int(config["INFERENCE_NUM_THREADS"]))]
    if data_shapes:
        args += ["-data_shape", ",".join(f"{name}[{','.join(map(str, shape))}]" for name, shape in data_shapes.items())]
    rest = {key: value for key, value in config.items() if key not in _FLAG_PROPERTIES}
    if rest:
        config_file.write_text(json.dumps({"CPU": rest}), encoding="utf-8")
        args += ["-load_config", str(config_file)]
    return args


def parse_benchmark_app_report(report: Mapping[str, Any]) -> tuple[float, int]:
    """(median ms, iterations) from benchmark_app's `-json_stats` report."""
    results = report.get("execution_results") or {}
    try:
        return float(results["latency (ms)"]), int(results["total number of iterations"])
    except (KeyError, TypeError, ValueError) as exc:
        raise OutsideToolError(f"benchmark_app report lacks its median latency or iteration count ({exc!r}); "
                               f"execution_results: {dict(results)}") from None


def run_benchmark_app(model: Path, config: Mapping[str, Any], seconds: float, work: Path,
                      inputs: Mapping[str, np.ndarray], dynamic: bool) -> OutsideFigure:
    """benchmark_app on `model` (an IR or ONNX file) with the target's `config`, fed `inputs`
    (batch 1); files go under `work`."""
    if not benchmark_app_available():
        return OutsideFigure(BENCHMARK_APP, reason="openvino.tools.benchmark is not installed (pip install openvino)")
    work.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, value in inputs.items():
        paths[name] = work / f"{_file_safe(name)}.npy"
        np.save(paths[name], np.ascontiguousarray(value))
    shapes = {name: value.shape for name, value in inputs.items()} if dynamic else None
    args = benchmark_app_args(model, config, seconds, work, paths, shapes, work / "config.json")
    command = [sys.executable, "-c", "import sys; from openvino.tools.benchmark.main import main; sys.exit(main())",
               *args]
    shown = " ".join([BENCHMARK_APP, *args])
    failure = _run(command, seconds + _START_UP_SECONDS, work / "benchmark_app.log")
    if failure:
        return OutsideFigure(BENCHMARK_APP, command=shown, reason=failure)
    try:
        report = json.loads((work / "benchmark_report.json").read_text(encoding="utf-8"))
        p50, runs = parse_benchmark_app_report(report)
        executed = exec_graph_layers(work / EXEC_GRAPH)
    except (OSError, ValueError, OutsideToolError, ElementTree.ParseError) as exc:
        return OutsideFigure(BENCHMARK_APP, command=shown, reason=f"unreadable report: {str(exc)[:300]}")
    return OutsideFigure(BENCHMARK_APP, p50, runs, shown, executed=executed)


def exec_graph_layers(path: Path) -> dict[str, int]:
    """The heavy layers of an executed graph benchmark_app wrote (`-exec_graph_path`) by
    run-time precision, counted as `runtime.openvino_session.count_heavy_layers` counts a
    compiled model's: each `<layer type=...>` with its `<data runtimePrecision=...>`."""
    from e3dpsm.runtime.openvino_session import count_heavy_layers

    def precision(layer: ElementTree.Element) -> str:
        data = layer.find("data")
        return UNKNOWN_PRECISION if data is None else data.get("runtimePrecision", UNKNOWN_PRECISION)

    root = ElementTree.parse(path).getroot()
    return count_heavy_layers((layer.get("type"), precision(layer)) for layer in root.iter("layer"))


def _file_safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


# -- ONNX Runtime --------------------------------------------------------------------------
def perf_test_path() -> str | None:
    return shutil.which(PERF_TEST)


def perf_test_args(graph: Path, threads: int, seconds: float, dynamic: bool) -> list[str]:
    """Random inputs (-I), free dimensions at 1 (`-f batch:1`: the graphs' batch axis is named
    "batch"), the profile's thread counts, statistics printed (-s)."""
    args = ["-m", "duration", "-t", str(max(1, round(seconds))), "-e", "cpu", "-x", str(threads), "-y", "1", "-I", "-s"]
    if dynamic:
        args += ["-f", "batch:1"]
    return [*args, str(graph)]


_PERF_TEST_P50 = re.compile(r"^P50 Latency:\s*([0-9.eE+-]+)\s*s\s*$", re.M)
_PERF_TEST_RUNS = re.compile(r"^Total inference requests:\s*(\d+)\s*$", re.M)


def parse_perf_test_output(text: str) -> tuple[float, int | None]:
    """(median ms, runs) from onnxruntime_perf_test's output (its "P50 Latency: <s> s" line,
    onnxruntime/test/perftest/performance_runner.cc)."""
    p50 = _PERF_TEST_P50.search(text)
    if p50 is None:
        raise OutsideToolError("onnxruntime_perf_test printed no 'P50 Latency' line (was -s given?)")
    runs = _PERF_TEST_RUNS.search(text)
    return float(p50.group(1)) * 1e3, int(runs.group(1)) if runs else None


def run_perf_test(graph: Path, threads: int, seconds: float, dynamic: bool, work: Path) -> OutsideFigure:
    tool = perf_test_path()
    if tool is None:
        return OutsideFigure(PERF_TEST, reason=f"{PERF_TEST} is not on PATH (not in the onnxruntime wheel)")
    args = perf_test_args(graph, threads, seconds, dynamic)
    shown = " ".join([PERF_TEST, *args])
    work.mkdir(parents=True, exist_ok=True)
    log = work / "perf_test.log"
    failure = _run([tool, *args], seconds + _START_UP_SECONDS, log)
    if failure:
        return OutsideFigure(PERF_TEST, command=shown, reason=failure)
    try:
        p50, runs = parse_perf_test_output(log.read_text(encoding="utf-8", errors="replace"))
    except OutsideToolError as exc:
        return OutsideFigure(PERF_TEST, command=shown, reason=str(exc))
    return OutsideFigure(PERF_TEST, p50, runs, shown)


# -- subprocess ----------------------------------------------------------------------------
def _run(command: list[str], timeout_s: float, log: Path) -> str | None:
    """Run `command`, its output to `log`; None on success, else why it failed."""
    try:
        with open(log, "w", encoding="utf-8") as out:
            completed = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        return f"timed out after {timeout_s:.0f} s"
    except OSError as exc:
        return f"could not start: {exc.strerror}"
    if completed.returncode != 0:
        lines = [line for line in log.read_text(encoding="utf-8", errors="replace").splitlines() if line.strip()]
        errors = [line for line in lines if "error" in line.lower() or "exception" in line.lower()]
        return f"exit {completed.returncode}: {(errors or lines or ['no output'])[-1].strip()[:300]}"
    return None
