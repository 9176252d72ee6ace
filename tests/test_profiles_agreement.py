"""The profile's figures beside the runtimes' own timers: the step split into the runtime's
call and its Python overhead (on an injected clock), the outside tools' arguments and
output parsing (on committed samples), and the verdict on injected timings."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from _timing_helpers import ManualClock
from e3dpsm.profiles.agreement import (NO_AGREEMENT, agreement_ratio, best_turn_agreement, combine_turns,
                                      measure_agreement, steady_turns, time_in_turns, turn_paired_agreement)
from e3dpsm.profiles.outside import (OutsideFigure, OutsideToolError, _run, benchmark_app_args,
                                     parse_benchmark_app_report, parse_perf_test_output, perf_test_args)
from e3dpsm.profiles.profiler import _record_times
from e3dpsm.profiles.step_timing import StepTimes, time_side_by_side
from e3dpsm.profiles.verdict import fastest_path, verdict_line

SAMPLES = Path(__file__).parent / "fixtures" / "outside_tools"


# -- the step split on an injected clock -----------------------------------------------------
class ScriptedRunner:
    """Each phase advances the fake clock by its scripted seconds for the current step."""

    def __init__(self, clock: ManualClock, prepare: list[float], run: list[float], collect: list[float]) -> None:
        self.clock, self.script, self.k = clock, {"prepare": prepare, "run": run, "collect": collect}, 0
        self.frames: list[float] = []

    def reset(self) -> None:
        self.k = 0

    def _tick(self, phase: str) -> None:
        self.clock.now += self.script[phase][self.k]

    def prepare(self, lnes: np.ndarray) -> None:
        self.frames.append(float(lnes[0, 0, 0, 0]))
        self._tick("prepare")

    def run(self) -> None:
        self._tick("run")

    def collect(self) -> None:
        self._tick("collect")
        self.k += 1

    def step(self, lnes: np.ndarray) -> None:  # warm-up steps: not on the script
        self.frames.append(float(lnes[0, 0, 0, 0]))


class StepOnlyRunner:
    def __init__(self, clock: ManualClock, seconds: float) -> None:
        self.clock, self.seconds = clock, seconds

    def reset(self) -> None:
        pass

    def step(self, lnes: np.ndarray) -> None:
        self.clock.now += self.seconds


def test_runtime_and_overhead_split_on_an_injected_clock() -> None:
    """Five steps, milliseconds by hand: prepare + run + collect = total; the runtime is the
    run alone, the overhead prepare + collect. Medians (odd count: the middle value):
    totals 12, 15, 11, 20, 13 -> 13; runtimes 10, 13, 10, 17, 11 -> 11; overheads 2, 2, 1, 3, 2 -> 2."""
    clock = ManualClock()
    ms = 1e-3
    phased = ScriptedRunner(clock, prepare=[1 * ms, 1 * ms, 0.5 * ms, 2 * ms, 1 * ms],
                            run=[10 * ms, 13 * ms, 10 * ms, 17 * ms, 11 * ms],
                            collect=[1 * ms, 1 * ms, 0.5 * ms, 1 * ms, 1 * ms])
    plain = StepOnlyRunner(clock, 7 * ms)
    frames = np.arange(4, dtype=np.float32).reshape(4, 1, 1, 1)
    times = time_side_by_side({"phased": phased, "plain": plain}, frames, steps=5, warmup=2, chunk=2, clock=clock)

    np.testing.assert_allclose(times["phased"].total / ms, [12, 15, 11, 20, 13])
    np.testing.assert_allclose(times["phased"].runtime / ms, [10, 13, 10, 17, 11])
    np.testing.assert_allclose(times["phased"].overhead / ms, [2, 2, 1, 3, 2])
    assert times["plain"].runtime is None and times["plain"].overhead is None
    np.testing.assert_allclose(times["plain"].total / ms, [7] * 5)
    assert phased.frames == [0.0, 1.0, 2.0, 3.0, 0.0, 1.0, 2.0]  # warm-up frames 0, 1; timed 2, 3, 0, 1, 2

    entry = {"flops": 2e9}
    _record_times(entry, times["phased"], peak_gflops=400.0)
    assert entry["latency_ms"]["p50"] == pytest.approx(13.0)
    assert entry["runtime_ms"]["p50"] == pytest.approx(11.0)
    assert entry["overhead_ms"]["p50"] == pytest.approx(2.0)
    assert entry["overhead_ms"]["p90"] == pytest.approx(2.6)  # numpy's linear interpolation: 2 + 0.6 * (3 - 2)
    assert entry["hz"] == pytest.approx(1e3 / 13.0)
    assert entry["gflops_achieved"] == pytest.approx(2e9 / 0.013 / 1e9)
    assert entry["peak_fraction"] == pytest.approx(entry["gflops_achieved"] / 400.0)


def test_turn_paired_speedup_cancels_drift_between_rounds() -> None:
    """Rounds of 2 steps; the host slows 3x from the second round on, the candidate's rounds
    land on the slow stretch later than the reference's. Per round: 2/1, 6/1, 6/3 -> median 2
    (the candidate is twice as fast in every round it shares with the reference); the ratio of
    whole-run medians would say 6 (reference median 6, candidate median 1)."""
    from e3dpsm.profiles.profiler import _ratios
    from e3dpsm.profiles.step_timing import turn_paired_speedup

    candidate = np.array([1.0, 1.0, 1.0, 1.0, 3.0, 3.0])
    reference = np.array([2.0, 2.0, 6.0, 6.0, 6.0, 6.0])
    assert turn_paired_speedup(candidate, reference, chunk=2) == pytest.approx(2.0)
    assert np.median(reference) / np.median(candidate) == pytest.approx(6.0)
    assert turn_paired_speedup(candidate[:5], reference[:5], chunk=2) == pytest.approx(2.0)  # a short last round
    with pytest.raises(ValueError, match="equally long"):
        turn_paired_speedup(candidate, reference[:4], chunk=2)
    entries = [{"name": "ort-cpu-fp32", "latency_ms": {"p50": 6.0}}, {"name": "fast", "latency_ms": {"p50": 1.0}},
               {"name": "gone", "latency_ms": None}]
    times = {"ort-cpu-fp32": StepTimes(reference), "fast": StepTimes(candidate)}
    assert _ratios(entries, times, chunk=2) == {"fast vs ort-cpu-fp32": pytest.approx(2.0)}


def test_step_only_runner_records_no_split() -> None:
    entry = {"flops": 1e9}
    _record_times(entry, StepTimes(np.array([0.004, 0.002, 0.003])), peak_gflops=100.0)
    assert entry["latency_ms"]["p50"] == pytest.approx(3.0) and "runtime_ms" not in entry


# -- the verdict on injected timings ---------------------------------------------------------
def _entry(name: str, p50: float | None, available: bool = True) -> dict:
    return {"name": name, "available": available, "latency_ms": None if p50 is None else {"p50": p50}}


def test_verdict_names_the_fastest_measured_target_and_its_rate() -> None:
    entries = [_entry("ort-cpu-fp32", 23.0), _entry("openvino-cpu-fp32", 22.2),
               _entry("openvino-cpu-fp32-static", 18.7), _entry("ort-cuda-fp32", None, available=False)]
    verdict = fastest_path(entries)
    assert verdict["fastest"] == "openvino-cpu-fp32-static"
    assert verdict["hz"] == pytest.approx(1e3 / 18.7) and verdict["p50_ms"] == 18.7
    assert verdict["tied"] == [] and verdict["not_measured"] == ["ort-cuda-fp32"]
    assert [r["name"] for r in verdict["ranking"]] == ["openvino-cpu-fp32-static", "openvino-cpu-fp32", "ort-cpu-fp32"]
    line = verdict_line(verdict)
    assert "`openvino-cpu-fp32-static`" in line and "53.5 Hz" in line


def test_verdict_ties_at_the_threshold() -> None:
    """3% of 20 ms is 0.6 ms: 20.59 ms is a tie, 20.61 ms is not."""
    verdict = fastest_path([_entry("a", 20.0), _entry("b", 20.59), _entry("c", 20.61)], tie_fraction=0.03)
    assert verdict["fastest"] == "a" and verdict["tied"] == ["b"]
    assert "Within 3% of it" in verdict_line(verdict) and "`b`" in verdict_line(verdict)
    exactly = fastest_path([_entry("a", 4.0), _entry("b", 5.0)], tie_fraction=0.25)  # 4 * 1.25 = 5, exact in binary
    assert exactly["tied"] == ["b"]  # the bound is inclusive
    equal = fastest_path([_entry("first", 10.0), _entry("second", 10.0)])
    assert equal["fastest"] == "first" and equal["tied"] == ["second"]


def test_verdict_skips_unavailable_targets() -> None:
    """An entry marked unavailable never wins, even with a figure left in it."""
    stale = {"name": "failed", "available": False, "latency_ms": {"p50": 1.0}}
    verdict = fastest_path([stale, _entry("ort-cpu-fp32", 21.5)])
    assert verdict["fastest"] == "ort-cpu-fp32" and verdict["not_measured"] == ["failed"]
    assert fastest_path([_entry("x", None, available=False)]) is None
    assert "No target ran" in verdict_line(None)


# -- outside tools: arguments and parsing -----------------------------------------------------
def test_benchmark_app_arguments_carry_the_targets_compile_properties(tmp_path: Path) -> None:
    config = {"INFERENCE_PRECISION_HINT": "bf16", "DYNAMIC_QUANTIZATION_GROUP_SIZE": 0, "PERFORMANCE_HINT": "LATENCY",
              "INFERENCE_NUM_THREADS": 2}
    inputs = {"lnes": tmp_path / "lnes.npy", "window_ms": tmp_path / "window_ms.npy"}
    args = benchmark_app_args(tmp_path / "step.xml", config, 4.6, tmp_path, inputs, {"lnes": (1, 2, 4, 4), "window_ms": (1,)},
                              tmp_path / "config.json")
    flag = {args[i]: args[i + 1] for i in range(len(args) - 1) if args[i].startswith("-")}
    assert (flag["-hint"], flag["-nstreams"], flag["-api"], flag["-nthreads"]) == ("none", "1", "sync", "2")
    assert flag["-infer_precision"] == "bf16" and flag["-t"] == "5" and flag["-inference_only"] == "true"
    assert flag["-data_shape"] == "lnes[1,2,4,4],window_ms[1]"
    # the file compiled as it is (no PrePostProcessor: it dequantises INT8 graphs), and the
    # graph it executed written beside the report
    assert "-lfile" in args and flag["-exec_graph_path"] == str(tmp_path / "exec_graph.xml")
    assert flag["-i"] == f"lnes:{tmp_path / 'lnes.npy'},window_ms:{tmp_path / 'window_ms.npy'}"
    # what no flag says travels in -load_config, and only that
    assert json.loads(Path(flag["-load_config"]).read_text()) == {"CPU": {"DYNAMIC_QUANTIZATION_GROUP_SIZE": 0}}
    static = benchmark_app_args(tmp_path / "s.xml", {"INFERENCE_NUM_THREADS": 1}, 2, tmp_path, inputs, None,
                                tmp_path / "c2.json")
    assert "-data_shape" not in static and "-load_config" not in static and "f32" in static


def test_benchmark_app_report_parsed_from_a_committed_sample() -> None:
    """benchmark_app_report.json: a real `-json_stats` report of benchmark_app (OpenVINO
    2026.4) on the tiny static graph, paths trimmed."""
    report = json.loads((SAMPLES / "benchmark_app_report.json").read_text())
    assert parse_benchmark_app_report(report) == (30.91, 32)
    del report["execution_results"]["latency (ms)"]
    with pytest.raises(OutsideToolError, match="median latency"):
        parse_benchmark_app_report(report)
    with pytest.raises(OutsideToolError):
        parse_benchmark_app_report({})


def test_benchmark_app_executed_graph_counted_from_a_committed_sample() -> None:
    """exec_graph.xml: eight layers of the executed graph benchmark_app wrote for `small`'s INT8
    graph (-exec_graph_path, OpenVINO 2026.4), ports kept, edges dropped. Counted here by a
    regular expression over the text, apart from the XML reader under test."""
    import re

    from e3dpsm.profiles.outside import exec_graph_layers

    text = (SAMPLES / "exec_graph.xml").read_text()
    pairs = re.findall(r'<layer id="\d+" name="[^"]*" type="(\w+)">\s*<data [^>]*runtimePrecision="(\w+)"', text)
    assert len(pairs) == 8
    expected = {}
    for kind, precision in pairs:
        if kind in ("Convolution", "Deconvolution", "FullyConnected", "MatMul"):
            expected[f"{kind} {precision}"] = expected.get(f"{kind} {precision}", 0) + 1
    assert exec_graph_layers(SAMPLES / "exec_graph.xml") == expected == {
        "Convolution f32": 1, "Convolution u8": 2, "FullyConnected f32": 1, "FullyConnected u8": 1}


def test_perf_test_output_parsed_from_a_sample() -> None:
    """onnxruntime_perf_test.txt is written in the tool's output format (the lines of
    onnxruntime/test/perftest/performance_runner.cc, microsoft/onnxruntime); the tool
    itself is not in the pip wheel."""
    text = (SAMPLES / "onnxruntime_perf_test.txt").read_text()
    p50, runs = parse_perf_test_output(text)
    assert p50 == pytest.approx(20.1223) and runs == 243
    with pytest.raises(OutsideToolError, match="P50 Latency"):
        parse_perf_test_output(text.replace("P50 Latency", "P55 Latency"))
    assert perf_test_args(Path("g.onnx"), 2, 5, dynamic=True)[-3:] == ["-f", "batch:1", "g.onnx"]
    assert "-f" not in perf_test_args(Path("g.onnx"), 2, 5, dynamic=False)


def test_agreement_ratio() -> None:
    figure = OutsideFigure("benchmark_app", p50_ms=20.0, runs=50)
    assert agreement_ratio(21.0, figure) == pytest.approx(1.05)
    assert agreement_ratio(21.0, OutsideFigure("x", reason="failed")) is None and agreement_ratio(None, figure) is None
    assert agreement_ratio(5.0, OutsideFigure("x", p50_ms=0.0)) is None


# -- the runner and the outside tool in turns ------------------------------------------------
class ScriptedTool:
    """An outside tool whose turns are logged beside the runner's steps; `fail_at`: the turn
    that fails."""

    tool = "tool"

    def __init__(self, log: list, medians: list[float], fail_at: int | None = None,
                 executed: dict[str, int] | None = None) -> None:
        self.log, self.medians, self.fail_at, self.turns = log, medians, fail_at, []
        self.executed = executed

    def turn(self, index: int) -> str | None:
        self.log.append(f"turn {index}")
        failed = index == self.fail_at
        self.turns.append(OutsideFigure("tool", None if failed else self.medians[index], None if failed else 10,
                                        reason="exit 1: boom" if failed else None, executed=self.executed))
        return self.turns[-1].reason

    def figure(self) -> OutsideFigure:
        return combine_turns("tool", self.turns)


class LoggedRunner(ScriptedRunner):
    def __init__(self, clock: ManualClock, log: list, run_ms: list[float]) -> None:
        n = len(run_ms)
        super().__init__(clock, [0.0] * n, [v * 1e-3 for v in run_ms], [0.0] * n)
        self.log = log

    def step(self, lnes: np.ndarray) -> None:
        super().step(lnes)
        self.log.append("warm-up")

    def run(self) -> None:
        super().run()
        self.log.append("timed")


def test_runner_bursts_bracket_the_tools_turns_on_an_injected_clock() -> None:
    """Turns 2, steps 2, one untimed warm-up step per burst: warm-up, timed, timed, turn 0,
    warm-up, timed, timed, turn 1, warm-up, timed, timed. The runner's median is over its
    timed runs only (6, 7, 9, 10, 11, 30 ms -> 9.5); the tool's is the median of its turns'."""
    clock, log = ManualClock(), []
    runner = LoggedRunner(clock, log, [6, 7, 9, 10, 11, 30])
    tool = ScriptedTool(log, [8.0, 12.0])
    frames = np.arange(5, dtype=np.float32).reshape(5, 1, 1, 1)
    figure, own = time_in_turns(runner, tool, frames, turns=2, steps=2, clock=clock, warmup=1)

    assert log == ["warm-up", "timed", "timed", "turn 0", "warm-up", "timed", "timed", "turn 1",
                   "warm-up", "timed", "timed"]
    np.testing.assert_allclose(own * 1e3, [[6, 7], [9, 10], [11, 30]])
    assert runner.frames == [0, 1, 2, 3, 4, 0, 1, 2, 3]  # one frame sequence across the bursts, warm-ups included
    assert (figure.p50_ms, figure.runs, figure.round_p50_ms) == (10.0, 20, (8.0, 12.0))
    assert agreement_ratio(1e3 * float(np.median(own)), figure) == pytest.approx(9.5 / 10.0)
    # The fastest burst (median 6.5 ms) over the fastest turn (8 ms): both sides' least disturbed.
    bursts = [1e3 * float(np.median(burst)) for burst in own]
    assert bursts == pytest.approx([6.5, 9.5, 20.5])
    assert best_turn_agreement(bursts, figure) == pytest.approx(6.5 / 8.0)
    assert best_turn_agreement(bursts, OutsideFigure("profiler", 13.0)) == pytest.approx(6.5 / 13.0)  # no turns
    assert best_turn_agreement([], figure) is None and best_turn_agreement(bursts, OutsideFigure("x")) is None
    # Turn-paired: the bursts around either turn differ by more than 10% (6.5 and 9.5; 9.5 and 20.5).
    assert turn_paired_agreement(bursts, figure) is None


def test_turn_paired_agreement_is_over_the_turns_with_steady_bursts_around_them() -> None:
    """The pipeline profile's `openvino-cpu-bf16` of 2026-12-05 (vnni host): the last burst ran at
    the host's fast speed, which none of the tool's turns reached. Fastest over fastest reads 0.745;
    the turn-paired figure leaves out turn 2 (bursts 12.70 and 8.90 differ by more than 10%) and
    is the median of the two pairs written out here."""
    bursts, turns = [12.56, 12.36, 12.70, 8.90], (12.19, 11.95, 12.09)
    figure = OutsideFigure("benchmark_app", float(np.median(turns)), round_p50_ms=turns)
    assert steady_turns(bursts) == [0, 1]
    pairs = [(12.56 + 12.36) / 2 / 12.19, (12.36 + 12.70) / 2 / 11.95]
    assert turn_paired_agreement(bursts, figure) == pytest.approx(np.mean(pairs)) == pytest.approx(1.0354, abs=1e-4)
    assert best_turn_agreement(bursts, figure) == pytest.approx(8.90 / 11.95)
    # A fast turn between steady bursts (a switch and a switch back within it) moves one pair only.
    fast = OutsideFigure("benchmark_app", 10.0, round_p50_ms=(10.0, 7.0, 10.0))
    assert turn_paired_agreement([10.0, 10.0, 10.0, 10.0], fast) == pytest.approx(1.0)
    # Which bursts a turn pairs with: the bursts before and after it, not any two.
    ordered = OutsideFigure("benchmark_app", 4.0, round_p50_ms=(2.0, 2.1, 2.2))
    assert turn_paired_agreement([2.0, 2.0, 2.2, 2.2], ordered) == pytest.approx(1.0)
    # Two speeds, each turn timed at the speed of the bursts around it when they are steady: the
    # 2026-12-05 `paper` stateful target (bursts 36.64, 25.30, 25.38, 36.72, 36.68 ms).
    paper = OutsideFigure("benchmark_app", 25.2, round_p50_ms=(25.06, 25.18, 25.23, 36.49))
    bursts = [36.64, 25.30, 25.38, 36.72, 36.68]
    assert steady_turns(bursts) == [1, 3]
    assert turn_paired_agreement(bursts, paper) == pytest.approx(np.mean([25.34 / 25.18, 36.70 / 36.49]))
    # Steady means within 10%, either way round: 10% apart is steady, a little more is not.
    assert steady_turns([10.0, 11.0, 10.0, 11.0001, 10.0]) == [0, 1]
    assert steady_turns([11.0, 10.0]) == [0] and steady_turns([11.0001, 10.0]) == []
    # No steady turn: no figure. No per-turn medians (ONNX Runtime's profiler): the bursts' median over
    # its one figure; turns and bursts that do not bracket each other, or no bursts: no figure.
    assert turn_paired_agreement([10.0, 20.0, 10.0], OutsideFigure("x", 10.0, round_p50_ms=(10.0, 10.0))) is None
    assert turn_paired_agreement([6.0, 9.0, 30.0], OutsideFigure("profiler", 12.0)) == pytest.approx(9.0 / 12.0)
    assert turn_paired_agreement([], OutsideFigure("profiler", 12.0)) is None
    assert turn_paired_agreement([1.0, 1.0], figure) is None
    assert turn_paired_agreement([1.0, 1.0], OutsideFigure("x", 1.0, round_p50_ms=(0.0,))) is None
    # Sub-millisecond tools count (a turn's median of 0.5 ms is a figure, not a failure).
    fast_tool = OutsideFigure("x", 0.5, round_p50_ms=(0.5, 0.5))
    assert turn_paired_agreement([0.55, 0.55, 0.55], fast_tool) == pytest.approx(1.1)


def test_a_failed_turn_ends_the_turns_and_gives_no_figure() -> None:
    clock, log = ManualClock(), []
    runner = LoggedRunner(clock, log, [5.0] * 6)
    tool = ScriptedTool(log, [8.0, 12.0, 9.0], fail_at=1)
    figure, own = time_in_turns(runner, tool, np.zeros((2, 1, 1, 1), np.float32), turns=3, steps=1, clock=clock,
                                warmup=0)
    assert [entry for entry in log if entry.startswith("turn")] == ["turn 0", "turn 1"]
    assert own.shape == (3, 1)  # before each turn run, and the closing burst
    assert figure.p50_ms is None and figure.reason == "turn 2 of 2: exit 1: boom"
    assert agreement_ratio(5.0, figure) is None


def test_turns_combine_into_the_median_of_their_medians() -> None:
    turns = [OutsideFigure("benchmark_app", 10.0, 100, "cmd"), OutsideFigure("benchmark_app", 30.0, 40, "cmd"),
             OutsideFigure("benchmark_app", 12.0, 90, "cmd")]
    figure = combine_turns("benchmark_app", turns)
    assert (figure.p50_ms, figure.runs, figure.command, figure.round_p50_ms) == (12.0, 230, "cmd", (10.0, 30.0, 12.0))
    assert combine_turns("benchmark_app", []).reason == "the tool did not run"


def test_targets_without_an_outside_timer_say_why(tiny_static_graph: Path) -> None:
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.targets import load_targets

    targets = load_targets()
    frames = moving_edge_frames(1, 192, 256, 20.0)
    eager = measure_agreement(None, targets["torch-eager-cpu"], None, frames, 1.0, 3, 2)
    assert eager == {"outside": OutsideFigure("-", reason="no outside timer for torch").to_dict(), **NO_AGREEMENT}
    profiler_off = measure_agreement(object(), targets["ort-cpu-fp32-static"], tiny_static_graph, frames, 1.0, 0, 2)
    assert profiler_off["outside"]["reason"] == "no profiled run (--profile-steps 0)"
    assert profiler_off["agreement"] is None


def test_onnxruntime_profiler_in_turns_on_the_tiny_static_graph(tiny_static_graph: Path) -> None:
    """Without onnxruntime_perf_test the profiler is ONNX Runtime's timer: 6 profiled steps in
    3 turns of 2, timed in turns with the target's own runner (2 steps a burst, 4 bursts)."""
    from e3dpsm.profiles.latency import OrtRunner
    from e3dpsm.profiles.outside import ORT_PROFILER, perf_test_path
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.targets import load_targets

    if perf_test_path() is not None:
        pytest.skip("onnxruntime_perf_test is on PATH: it, not the profiler, is the outside timer")
    target = load_targets()["ort-cpu-fp32-static"]
    frames = moving_edge_frames(4, 192, 256, 20.0)
    runner = OrtRunner(str(tiny_static_graph), target, frames.window_ms, side_by_side=True)
    runner.reset()
    result = measure_agreement(runner, target, tiny_static_graph, frames, 1.0, 6, 2, turns=3)
    outside = result["outside"]
    assert outside["tool"] == ORT_PROFILER and outside["reason"] is None and outside["runs"] == 6
    assert 0 < outside["p50_ms"] < 1e3 and outside["note"].startswith("kernels alone ")
    assert 0 < result["beside_ms"] < 1e3 and len(result["beside_burst_ms"]) == 4
    assert result["agreement_median"] == pytest.approx(result["beside_ms"] / outside["p50_ms"])
    assert result["agreement_fastest"] == pytest.approx(min(result["beside_burst_ms"]) / outside["p50_ms"])
    # The profiler has no per-turn medians: the bursts' median over its figure.
    assert result["agreement"] == pytest.approx(np.median(result["beside_burst_ms"]) / result["outside"]["p50_ms"])
    assert result["agreement_steady_turns"] is None
    unphased = measure_agreement(StepOnlyRunner(ManualClock(), 0.001), target, tiny_static_graph, frames, 1.0, 6, 2,
                                 turns=3)
    assert unphased["outside"] == OutsideFigure(ORT_PROFILER, reason="the runner has no separate runtime call").to_dict()


def test_a_failing_outside_tool_is_one_line_of_reason(tmp_path: Path) -> None:
    failing = [sys.executable, "-c", "print('[ ERROR ] Model file does not exist'); raise SystemExit(3)"]
    assert _run(failing, 60, tmp_path / "log.txt") == "exit 3: [ ERROR ] Model file does not exist"
    assert _run([sys.executable, "-c", "print('fine')"], 60, tmp_path / "ok.txt") is None
    assert _run([str(tmp_path / "no-such-tool")], 60, tmp_path / "x.txt").startswith("could not start")


@pytest.mark.slow  # ~14 s on a loaded 2-core host: IR conversion, a fresh interpreter, compile, 1 s of steps
def test_benchmark_app_runs_on_the_tiny_static_graph(tiny_static_graph: Path, tmp_path: Path) -> None:
    pytest.importorskip("openvino")
    from e3dpsm.profiles.agreement import outside_timer
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.targets import load_targets

    timer = outside_timer(load_targets()["openvino-cpu-fp32-static"], tiny_static_graph,
                          moving_edge_frames(1, 192, 256, 20.0), 1, tmp_path, profiler_steps=0, turns=1)
    assert timer.turn(0) is None
    figure = timer.figure()
    assert figure.reason is None, figure.reason
    assert figure.tool == "benchmark_app" and figure.runs >= 1 and 0 < figure.p50_ms < 1e4
    report = json.loads((tmp_path / "turn0" / "benchmark_report.json").read_text())
    assert parse_benchmark_app_report(report) == (figure.p50_ms, figure.runs)
    assert report["configuration_setup"]["number of CPU streams"] == "1" and report["configuration_setup"]["inference_only"]
    assert (report["cmd_options"]["-nthreads"], report["cmd_options"]["-infer_precision"]) == ("2", "f32")
    assert "-data_shape" not in report["cmd_options"]  # a static graph runs as it is


# -- which outside timer each target gets, and with what (the tools themselves faked) ----------
class _Recorded:
    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def benchmark_app(self, model, config, seconds, work, inputs, dynamic):
        self.calls.append(("benchmark_app", model, dict(config), seconds, work.name, dict(inputs), dynamic))
        return OutsideFigure("benchmark_app", 10.0 + len(self.calls), 7, "cmd")

    def perf_test(self, graph, threads, seconds, dynamic, work):
        self.calls.append(("perf_test", graph, threads, seconds, dynamic, work.name))
        return OutsideFigure("onnxruntime_perf_test", 20.0, 5, "cmd")


@pytest.fixture()
def recorded(monkeypatch):
    import e3dpsm.profiles.agreement as agreement

    calls = _Recorded()
    monkeypatch.setattr(agreement, "run_benchmark_app", calls.benchmark_app)
    monkeypatch.setattr(agreement, "run_perf_test", calls.perf_test)
    monkeypatch.setattr(agreement, "_openvino_ir", lambda graph, stateful, work: Path(f"ir-stateful-{stateful}.xml"))
    return calls


@pytest.mark.parametrize("name, stateful", [("openvino-cpu-fp32", False), ("openvino-cpu-stateful-fp32-static", True)])
def test_benchmark_app_gets_the_targets_graph_inputs_and_turn_length(recorded, tiny_step_graph, tiny_static_graph,
                                                                     name, stateful):
    """8 s in 4 turns: 2 s a turn; the explicit-state graph is fed its initial states and kept
    dynamic (-data_shape), the stateful IR (static, batch 1) only the frame and the window."""
    from e3dpsm.profiles.agreement import outside_timer
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.latency import openvino_target_config
    from e3dpsm.profiles.targets import load_targets

    target = load_targets()[name]
    graph = tiny_static_graph if stateful else tiny_step_graph
    frames = moving_edge_frames(2, 192, 256, 20.0)
    timer = outside_timer(target, graph, frames, 8.0, Path("work"), profiler_steps=0, turns=4)
    assert timer.turn(0) is None and timer.turn(1) is None
    assert [c[4] for c in recorded.calls] == ["turn0", "turn1"]
    _, model, config, seconds, _, inputs, dynamic = recorded.calls[0]
    assert model == Path(f"ir-stateful-{stateful}.xml") and config == openvino_target_config(target)
    assert seconds == 2.0 and dynamic is (not stateful)
    assert sorted(inputs) == sorted(["lnes", "window_ms"] + ([] if stateful else [
        "s5_stage1_re_in", "s5_stage1_im_in", "s5_stage4_re_in", "s5_stage4_im_in", "fusion_pose_in",
        "fusion_cov_in", "fusion_initialised_in"]))
    np.testing.assert_array_equal(inputs["lnes"], frames.lnes[:1])
    figure = timer.figure()
    assert (figure.tool, figure.p50_ms, figure.runs, figure.round_p50_ms) == ("benchmark_app", 11.5, 14, (11.0, 12.0))


def test_perf_test_is_onnx_runtimes_timer_where_it_is_installed(recorded, monkeypatch, tiny_step_graph):
    import e3dpsm.profiles.agreement as agreement
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.targets import load_targets

    monkeypatch.setattr(agreement, "perf_test_path", lambda: "/opt/ort/onnxruntime_perf_test")
    timer = agreement.outside_timer(load_targets()["ort-cpu-fp32"], tiny_step_graph,
                                    moving_edge_frames(1, 192, 256, 20.0), 6.0, Path("w"), profiler_steps=0, turns=3)
    assert timer.turn(0) is None
    assert recorded.calls == [("perf_test", tiny_step_graph, 2, 2.0, True, "turn0")]
    assert timer.figure().tool == "onnxruntime_perf_test" and timer.figure().p50_ms == 20.0


def test_cpu_only_and_runs_without_a_count(tiny_step_graph) -> None:
    from e3dpsm.profiles.agreement import outside_timer
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.targets import load_targets

    gpu = outside_timer(load_targets()["ort-cuda-fp32"], tiny_step_graph, moving_edge_frames(1, 192, 256, 20.0),
                        5.0, Path("w"), profiler_steps=30)
    assert gpu == OutsideFigure("-", reason="outside timers are run for CPU targets only")
    turns = [OutsideFigure("t", 10.0, None), OutsideFigure("t", 12.0, 4)]
    assert combine_turns("t", turns).runs == 4  # a turn that counted no runs adds none
    assert agreement_ratio(1.0, OutsideFigure("x", p50_ms=0.5)) == pytest.approx(2.0)  # sub-millisecond tools count


def test_agreement_in_milliseconds_on_an_injected_clock(monkeypatch) -> None:
    """measure_agreement's figures in ms from the runner's seconds: bursts 6.5, 7.0, 7.0 ms around
    turns of 8 and 12 ms."""
    import e3dpsm.profiles.agreement as agreement
    from e3dpsm.profiles.inputs import Frames
    from e3dpsm.profiles.targets import load_targets

    clock, log = ManualClock(), []
    tool = ScriptedTool(log, [8.0, 12.0])
    monkeypatch.setattr(agreement, "outside_timer", lambda *args, **kwargs: tool)
    runner = LoggedRunner(clock, log, [6, 7, 6.5, 7.5, 7, 7])
    frames = Frames(np.zeros((3, 1, 1, 1), np.float32), 20.0, "test")
    result = measure_agreement(runner, load_targets()["openvino-cpu-fp32"], Path("g.onnx"), frames, 4.0, 0, 2,
                               turns=2, clock=clock)
    assert result["beside_ms"] == pytest.approx(7.0) and result["beside_burst_ms"] == pytest.approx([6.5, 7.0, 7.0])
    assert result["agreement"] == pytest.approx(np.mean([(6.5 + 7.0) / 2 / 8.0, (7.0 + 7.0) / 2 / 12.0]))
    assert result["agreement_steady_turns"] == 2
    assert result["agreement_fastest"] == pytest.approx(6.5 / 8.0)
    assert result["agreement_median"] == pytest.approx(7.0 / 10.0)
    assert tuple(result["outside"]["round_p50_ms"]) == (8.0, 12.0)


class _CompiledModel:
    """What executed_layers reads of an OpenVINO compiled model: its run-time graph's ops and
    their `layerType` / `runtimePrecision`."""

    class _Op:
        def __init__(self, kind: str, precision: str) -> None:
            self.info = {"layerType": kind, "runtimePrecision": precision}

        def get_rt_info(self) -> dict[str, str]:
            return self.info

    def __init__(self, *layers: tuple[str, str]) -> None:
        self.ops = [self._Op(*layer) for layer in layers]

    def get_runtime_model(self) -> "_CompiledModel":
        return self

    def get_ops(self) -> list:
        return self.ops


EXECUTED = {"Convolution u8": 2, "FullyConnected f32": 1}


@pytest.mark.parametrize("runner_layers, executed, runner_counts", [
    ((("Convolution", "u8"), ("Convolution", "u8"), ("Eltwise", "f32"), ("FullyConnected", "f32")), EXECUTED, None),
    ((("Convolution", "f32"), ("Convolution", "u8"), ("FullyConnected", "f32")), EXECUTED,  # one conv in f32
     "Convolution f32 x1, Convolution u8 x1, FullyConnected f32 x1"),
    ((("Convolution", "u8"), ("MatMul", "f32"), ("Convolution", "u8"), ("FullyConnected", "f32")), EXECUTED,
     "Convolution u8 x2, FullyConnected f32 x1, MatMul f32 x1"),
    ((("Eltwise", "f32"),), EXECUTED, "no heavy layers"),
    (None, EXECUTED, None),  # a runner with no OpenVINO compiled model: nothing to compare
    ((("Convolution", "f32"),), None, None),  # a tool that reported no executed graph
])
def test_a_tool_that_executed_another_graph_is_not_compared(monkeypatch, runner_layers, executed,
                                                            runner_counts) -> None:
    """The tool's executed graph against the runner's compiled model, heavy layers by run-time
    precision (other layers do not count): equal, or either side unknown (`runner_counts`
    None), the figures are compared; else the figure is kept, with a note naming both, and no
    agreement is given."""
    import e3dpsm.profiles.agreement as agreement
    from e3dpsm.profiles.inputs import Frames
    from e3dpsm.profiles.targets import load_targets

    clock, log = ManualClock(), []
    monkeypatch.setattr(agreement, "outside_timer", lambda *args, **kwargs: ScriptedTool(log, [8.0, 12.0],
                                                                                         executed=executed))
    runner = LoggedRunner(clock, log, [6, 7, 9, 10, 11, 30])
    if runner_layers is not None:
        runner.compiled = _CompiledModel(*runner_layers)
    frames = Frames(np.zeros((3, 1, 1, 1), np.float32), 20.0, "test")
    result = measure_agreement(runner, load_targets()["openvino-cpu-int8"], Path("g.onnx"), frames, 4.0, 0, 2,
                               turns=2, clock=clock)
    assert result["beside_ms"] == pytest.approx(9.5) and result["outside"]["executed"] == executed
    assert result["beside_burst_ms"] == pytest.approx([6.5, 9.5, 20.5])
    assert result["outside"]["p50_ms"] == pytest.approx(10.0)
    if runner_counts is None:
        assert result["agreement"] is None and result["agreement_steady_turns"] == 0  # no steady turn (6.5, 9.5, 20.5)
        assert result["agreement_fastest"] == pytest.approx(6.5 / 8.0) and result["outside"]["note"] is None
    else:
        assert result["agreement"] is None and result["agreement_median"] is None and result["agreement_fastest"] is None
        assert result["agreement_steady_turns"] is None
        assert result["outside"]["note"] == ("not compared: tool executed another graph (Convolution u8 x2, "
                                             f"FullyConnected f32 x1) than the runner ({runner_counts})")


def test_a_runner_without_phases_gets_the_tools_name_and_a_reason(monkeypatch) -> None:
    import e3dpsm.profiles.agreement as agreement
    from e3dpsm.profiles.inputs import Frames
    from e3dpsm.profiles.targets import load_targets

    class Tool:
        tool = "benchmark_app"

    monkeypatch.setattr(agreement, "outside_timer", lambda *args, **kwargs: Tool())
    frames = Frames(np.zeros((1, 1, 1, 1), np.float32), 20.0, "test")
    result = measure_agreement(StepOnlyRunner(ManualClock(), 0.001), load_targets()["openvino-cpu-fp32"],
                               Path("g.onnx"), frames, 4.0, 0, 2)
    assert result == {"outside": OutsideFigure("benchmark_app", reason="the runner has no separate runtime call")
                      .to_dict(), "beside_ms": None, "beside_burst_ms": None, "agreement": None,
                      "agreement_steady_turns": None, "agreement_fastest": None, "agreement_median": None}


def test_the_profiled_session_steps_its_frames_in_order(tiny_static_graph, tmp_path) -> None:
    """3 profiled steps in 3 turns of 1 (profile steps equal to the turns still profile); a
    session with no turn run says so; its threads stop spinning after each run, as the
    side-by-side runners' do."""
    from e3dpsm.profiles.agreement import ProfiledOrtRuns, outside_timer
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.targets import load_targets

    target = load_targets()["ort-cpu-fp32-static"]
    frames = moving_edge_frames(3, 192, 256, 20.0)
    timer = outside_timer(target, tiny_static_graph, frames, 1.0, tmp_path / "a" / "b", profiler_steps=3, turns=3)
    seen = []
    original = timer.runner.step
    timer.runner.step = lambda lnes: (seen.append(float(lnes.sum())), original(lnes))
    for k in range(3):
        assert timer.turn(k) is None
    assert seen == [float(frames.lnes[k].sum()) for k in range(3)] and len(set(seen)) == 3
    assert timer.figure().runs == 3
    options = timer.runner.session.session.get_session_options()
    assert options.get_session_config_entry("session.force_spinning_stop") == "1"
    idle = ProfiledOrtRuns(tiny_static_graph, target, frames, 2, tmp_path / "idle")
    assert idle.figure() == OutsideFigure("onnxruntime profiler (model_run)", reason="the profiled session recorded no run")


def test_the_documented_turns_and_warm_up_are_the_code_s() -> None:
    """docs/validate-and-profile.md states both numbers; the CLI's default is the constant."""
    from e3dpsm.cli import build_parser
    from e3dpsm.profiles.agreement import BURST_WARMUP, DEFAULT_TURNS

    text = " ".join((Path(__file__).parents[1] / "docs" / "validate-and-profile.md").read_text().split())
    assert f"`--outside-turns` turns (default {DEFAULT_TURNS})" in text
    assert f"a burst of steps (after {BURST_WARMUP} untimed ones)" in text
    args = build_parser().parse_args(["profile", "--model", "g.onnx", "--out", "o"])
    assert args.outside_turns == DEFAULT_TURNS == 3 and BURST_WARMUP == 3


def test_the_stateful_ir_benchmark_app_reads_is_batch_one(tiny_static_graph, tmp_path) -> None:
    import openvino as ov

    from e3dpsm.profiles.agreement import _openvino_ir, outside_timer
    from e3dpsm.profiles.inputs import moving_edge_frames
    from e3dpsm.profiles.targets import load_targets

    xml = _openvino_ir(tiny_static_graph, stateful=True, work=tmp_path / "nested" / "work")
    model = ov.Core().read_model(str(xml))
    assert [str(port.get_partial_shape()) for port in model.inputs if "lnes" in port.get_names()] == ["[1,2,192,256]"]
    assert model.get_sinks(), "stateful: the states are variables inside the IR"
    # PyTorch eager has no outside timer, whether or not a graph is at hand.
    eager = outside_timer(load_targets()["torch-eager-cpu"], tiny_static_graph, moving_edge_frames(1, 192, 256, 20.0),
                          1.0, tmp_path, profiler_steps=3)
    assert eager == OutsideFigure("-", reason="no outside timer for torch")


def test_the_printed_summary_gives_the_turn_paired_ratio_or_why_there_is_none() -> None:
    """`e3dpsm profile`'s printed lines: the turn-paired agreement where there is one; where the tool
    executed another graph than the runner (no ratio), the note saying so instead of a crash."""
    from e3dpsm.profiles.command import summary_lines

    def entry(name: str, agreement: float | None, note: str | None) -> dict:
        return {"name": name, "available": True, "latency_ms": {"p50": 10.0, "p90": 11.0, "p99": 12.0}, "hz": 100.0,
                "outside": {"tool": "benchmark_app", "p50_ms": 9.0, "note": note}, "beside_ms": 9.5,
                "agreement": agreement, "agreement_fastest": 0.5, "agreement_median": 0.7}

    note = "not compared: benchmark_app executed another graph (Convolution u8 x2) than the runner (Convolution f32 x2)"
    report = {"targets": [entry("openvino-cpu-fp32", 1.0234, None), entry("openvino-cpu-int8", None, note),
                          entry("openvino-cpu-bf16", None, None)], "ratios": {}}
    lines = summary_lines(report)
    assert lines[1].endswith("benchmark_app 9.00 ms against runtime 9.50 in turns with it (1.02x)")
    assert lines[2].endswith(f"benchmark_app 9.00 ms against runtime 9.50 in turns with it ({note})")
    assert lines[3].endswith("in turns with it (no ratio: the host changed speed across every turn)")


def test_the_report_cell_names_the_turns_the_agreement_is_over() -> None:
    from e3dpsm.profiles.report import turn_paired_cell

    outside = {"tool": "benchmark_app", "p50_ms": 9.0, "round_p50_ms": [9.0, 9.1, 12.0, 9.2]}
    assert turn_paired_cell({"outside": outside, "agreement": 1.01234, "agreement_steady_turns": 3}) == \
        "1.012 (3 of 4 turns)"
    assert turn_paired_cell({"outside": outside, "agreement": None, "agreement_steady_turns": 0}) == \
        "- (the runner's speed changed across each of the 4 turns)"
    profiler = {"tool": "onnxruntime profiler (model_run)", "p50_ms": 9.0, "round_p50_ms": None}
    assert turn_paired_cell({"outside": profiler, "agreement": 0.83456, "agreement_steady_turns": None}) == "0.835"
    assert turn_paired_cell({"outside": outside, "agreement": None, "agreement_steady_turns": None}) == "-"
    assert turn_paired_cell({"outside": outside, "agreement": None, "agreement_steady_turns": 2}) == "-"


def test_the_agreement_table_rows() -> None:
    from e3dpsm.profiles.report import agreement_table

    ov = {"name": "openvino-cpu-fp32", "latency_ms": {"p50": 10.0}, "runtime_ms": {"p50": 9.5}, "beside_ms": 9.25,
          "beside_burst_ms": [9.0, 9.5, 9.25], "agreement": 1.0123, "agreement_steady_turns": 2,
          "agreement_fastest": 0.98765, "agreement_median": 1.0049,
          "outside": {"tool": "benchmark_app", "p50_ms": 9.2, "round_p50_ms": [9.1, 9.3], "note": None}}
    profiler = {"name": "ort-cpu-fp32", "latency_ms": {"p50": 8.0}, "runtime_ms": None, "beside_ms": 7.5,
                "beside_burst_ms": [7.5], "agreement": 0.75, "agreement_steady_turns": None,
                "agreement_fastest": 0.75, "agreement_median": 0.75,
                "outside": {"tool": "onnxruntime profiler (model_run)", "p50_ms": 10.0, "round_p50_ms": None,
                            "note": "kernels alone 9 ms per step"}}
    failed = {**ov, "name": "openvino-cpu-int8", "agreement": None, "agreement_steady_turns": None,
              "agreement_fastest": None, "agreement_median": None,
              "outside": {"tool": "benchmark_app", "p50_ms": None, "reason": "exit 1: no model"}}
    rows = agreement_table([ov, profiler, failed, {"name": "ort-cuda-fp32", "latency_ms": None},
                            {"name": "torch-eager-cpu", "latency_ms": {"p50": 3.0}}])
    assert rows == [
        "| target | profile p50 ms (step, side by side) | runtime p50 ms (side by side) | runtime p50 ms (in turns with "
        "the tool; each burst) | outside timer | outside p50 ms (each turn) | runtime / outside, turn-paired | "
        "fastest burst / fastest turn | medians |", "|---|---|---|---|---|---|---|---|---|",
        "| openvino-cpu-fp32 | 10 | 9.5 | 9.25 (9, 9.5, 9.25) | benchmark_app | 9.2 (9.1, 9.3) | 1.012 (2 of 2 turns) | "
        "0.988 | 1 |",
        "| ort-cpu-fp32 | 8 | - | 7.5 | onnxruntime profiler (model_run) | 10; kernels alone 9 ms per step | 0.75 | "
        "0.75 | 0.75 |",
        "| openvino-cpu-int8 | 10 | 9.5 | 9.25 (9, 9.5, 9.25) | benchmark_app | - (exit 1: no model) | - | - | - |"]
    assert agreement_table([{"name": "ort-cuda-fp32", "latency_ms": None}]) == []
