"""Runtime session benchmarks (writes benchmarks/results/runtime_sessions.json and .md).

    python benchmarks/bench_runtime_sessions.py [--int8 small_int8.onnx] [--threads 2] [--quick]

1. Session overhead: per-step cost of each session kind on `tiny` and `small`: the plain
   numpy `StepSession` and `IOBindingStepSession`, taking turns in blocks of steps, states
   carried. Reported: the median step wall time and, measured directly, the median time
   per step spent OUTSIDE onnxruntime's run call (input checks, binding, state hand-over,
   output copies): the figure the session kind changes.
2. Many streams, one session: N = 1, 2, 4, 8 synthetic streams of ~8,000 events per 20 ms
   window, one window of events per stream per call, stream grids staggered. Throughput
   (poses per second of wall time) and p50 / p99 latency of one call (windowing + LNES +
   batched step) for `MultiStreamEstimator` against N `StreamingPoseEstimator`s sharing the
   session (batch-1 steps, the same work sequentially), on `small` and `paper`.
3. Runtime overhead budget: everything per pose except onnxruntime's run call (chunk
   validation, windowing, LNES, feeds, state handling, output split) as a % of the step of
   the `small` INT8 graph (`--int8`; without it, of the fp32 `small` graph, said in the
   report), at ~8,000 events per window, for each runtime path.

Graphs are exported untrained in a child process (timing does not depend on the weights),
so this process never imports torch, as on a device.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_runtime import export_variant  # noqa: E402  (same folder; exports in a child process)

from e3dpsm.runtime import IOBindingStepSession, MultiStreamEstimator, StepSession, StreamingPoseEstimator  # noqa: E402
from e3dpsm.utils.env import report_header  # noqa: E402
from e3dpsm.utils.io import write_json_atomic, write_text_atomic  # noqa: E402

WINDOW_US = 20_000
SENSOR_HW = (480, 640)
EVENTS_PER_WINDOW = 8_000
STREAM_COUNTS = (1, 2, 4, 8)
SESSION_KINDS: dict[str, Callable[..., StepSession]] = {"numpy": StepSession, "iobinding": IOBindingStepSession}


class TimedORT:
    """Stands in for the InferenceSession inside a StepSession and adds up the seconds spent
    inside its run calls, so the rest of a step is measured directly, not as a difference."""

    def __init__(self, inner: Any) -> None:
        self._inner = inner
        self.seconds = 0.0

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def run(self, *args: Any, **kwargs: Any) -> Any:
        began = time.perf_counter()
        try:
            return self._inner.run(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - began

    def run_with_iobinding(self, *args: Any, **kwargs: Any) -> Any:
        began = time.perf_counter()
        try:
            return self._inner.run_with_iobinding(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - began


def timed_session(kind: str, path: Path, threads: int) -> tuple[StepSession, TimedORT]:
    session = SESSION_KINDS[kind](path, threads=threads)
    timer = TimedORT(session.session)
    session.session = timer
    return session, timer


def sparse_frames(count: int, hw: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    mask = rng.random((count, 2, *hw)) < 0.05
    return (mask * rng.random((count, 2, *hw))).astype(np.float32)


# -- 1. session overhead --------------------------------------------------------------------------

def bench_session_overhead(path: Path, threads: int, steps: int, block: int = 10) -> dict:
    sessions = {kind: timed_session(kind, path, threads) for kind in SESSION_KINDS}
    frames = sparse_frames(16, sessions["numpy"][0].meta.frame_hw, seed=0)
    states = {kind: s.init_state(1) for kind, (s, _) in sessions.items()}
    wall: dict[str, list[float]] = {kind: [] for kind in sessions}
    outside: dict[str, list[float]] = {kind: [] for kind in sessions}
    for k in range(5):  # warm-up: ORT arenas, binding buffers
        for kind, (s, _) in sessions.items():
            _, states[kind] = s.step(frames[k % 16][None], states[kind], 20.0)
    for first in range(0, steps, block):  # the kinds take turns, so load changes hit both alike
        for kind, (s, timer) in sessions.items():
            for k in range(first, min(first + block, steps)):
                inside_before = timer.seconds
                began = time.perf_counter()
                _, states[kind] = s.step(frames[k % 16][None], states[kind], 20.0)
                seconds = time.perf_counter() - began
                wall[kind].append(seconds)
                outside[kind].append(seconds - (timer.seconds - inside_before))
    meta = sessions["numpy"][0].meta
    return {
        "variant": meta.config.get("variant"), "threads": threads, "steps_per_kind": steps,
        "state_floats": int(sum(np.prod(s.shape) for s in meta.states)),
        "kinds": {kind: {
            "median_step_ms": 1e3 * float(np.median(wall[kind])),
            "median_outside_ort_us": 1e6 * float(np.median(outside[kind])),
            "p90_outside_ort_us": 1e6 * float(np.percentile(outside[kind], 90)),
        } for kind in sessions},
    }


# -- 2. many streams --------------------------------------------------------------------------------

def window_chunks(windows: int, offset_us: int, seed: int) -> list[tuple[np.ndarray, ...]]:
    """One chunk per window [offset + kT, offset + (k+1)T), k = 0..windows (one extra so the
    last is closed), ~EVENTS_PER_WINDOW Poisson events each, canonical dtypes."""
    rng = np.random.default_rng(seed)
    chunks = []
    for k in range(windows + 1):
        n = max(1, int(rng.poisson(EVENTS_PER_WINDOW)))
        t = np.sort(offset_us + k * WINDOW_US + rng.integers(0, WINDOW_US, n))
        chunks.append((rng.integers(0, SENSOR_HW[1], n, dtype=np.int32),
                       rng.integers(0, SENSOR_HW[0], n, dtype=np.int32),
                       t.astype(np.int64), rng.integers(0, 2, n, dtype=np.uint8)))
    return chunks


def run_multi(session: StepSession, streams: list[list[tuple]], starts: list[int]) -> tuple[list[float], int]:
    estimator = MultiStreamEstimator(session, window_ms=WINDOW_US / 1000, sensor_hw=SENSOR_HW)
    for i, start in enumerate(starts):
        estimator.add_stream(i, start_us=start)
    latencies, poses = [], 0
    for k in range(len(streams[0])):
        began = time.perf_counter()
        out = estimator.push_many({i: chunks[k] for i, chunks in enumerate(streams)})
        latencies.append(time.perf_counter() - began)
        poses += sum(len(v) for v in out.values())
    return latencies, poses


def run_independent(session: StepSession, streams: list[list[tuple]], starts: list[int]) -> tuple[list[float], int]:
    estimators = [StreamingPoseEstimator(session, window_ms=WINDOW_US / 1000, start_us=start, sensor_hw=SENSOR_HW)
                  for start in starts]
    latencies, poses = [], 0
    for k in range(len(streams[0])):
        began = time.perf_counter()
        poses += sum(len(est.push(*chunks[k])) for est, chunks in zip(estimators, streams))
        latencies.append(time.perf_counter() - began)
    return latencies, poses


def bench_streams(path: Path, threads: int, windows: int, kinds: tuple[str, ...]) -> dict:
    sessions = {kind: SESSION_KINDS[kind](path, threads=threads) for kind in kinds}
    rows = []
    for n in STREAM_COUNTS:
        offsets = [(i * 7_919) % WINDOW_US for i in range(n)]  # staggered grids: windows end at other times
        streams = [window_chunks(windows, offset, seed=100 + i) for i, offset in enumerate(offsets)]
        warm = [window_chunks(2, offset, seed=900 + i) for i, offset in enumerate(offsets)]
        runners = {f"multi[{kind}]": (run_multi, sessions[kind]) for kind in kinds}
        runners["independent[numpy]"] = (run_independent, sessions["numpy"])
        for name, (runner, session) in runners.items():
            runner(session, warm, offsets)  # batch-N buffers and arenas allocated before timing
        measured: dict[str, tuple[list[float], int]] = {name: ([], 0) for name in runners}
        half = len(streams[0]) // 2  # two halves, runners alternating, to even out load changes
        for part in (slice(0, half + 1), slice(half, None)):
            for name, (runner, session) in runners.items():
                lat, poses = runner(session, [s[part] for s in streams], offsets)
                measured[name] = (measured[name][0] + lat[1:], measured[name][1] + poses)  # lat[0]: no window yet
        for name, (lat, poses) in measured.items():
            rows.append({
                "variant": sessions["numpy"].meta.config.get("variant"), "streams": n, "runner": name,
                "poses": poses, "seconds": float(np.sum(lat)), "poses_per_s": poses / float(np.sum(lat)),
                "p50_call_ms": 1e3 * float(np.median(lat)), "p99_call_ms": 1e3 * float(np.percentile(lat, 99)),
                "calls": len(lat),
            })
            print(f"  {rows[-1]['variant']} N={n} {name}: {rows[-1]['poses_per_s']:.1f} poses/s, "
                  f"p99 {rows[-1]['p99_call_ms']:.1f} ms", flush=True)
    return {"threads": threads, "windows_per_stream": windows, "events_per_window": EVENTS_PER_WINDOW,
            "rows": rows}


# -- 3. overhead budget -------------------------------------------------------------------------------

def bench_budget(path: Path, threads: int, windows: int) -> dict:
    chunks = window_chunks(windows, 0, seed=7)
    big = [tuple(np.concatenate(c) for c in zip(*chunks[lo:lo + 12])) for lo in range(0, len(chunks), 12)]
    paths: dict[str, dict] = {}
    for label, kind, multi in (("stream[numpy]", "numpy", False), ("stream[iobinding]", "iobinding", False),
                               ("multi x4[numpy]", "numpy", True), ("multi x4[iobinding]", "iobinding", True)):
        session, timer = timed_session(kind, path, threads)
        if multi:
            run_independent(session, [window_chunks(2, 0, 1)], [0])  # warm-up
            estimator = MultiStreamEstimator(session, window_ms=WINDOW_US / 1000, sensor_hw=SENSOR_HW)
            for i in range(4):
                estimator.add_stream(i, start_us=0)
            timer.seconds = 0.0
            began = time.perf_counter()
            poses = 0
            for chunk in big:  # ~100,000-event chunks, as `e3dpsm run` pushes them
                poses += sum(len(v) for v in estimator.push_many({i: chunk for i in range(4)}).values())
        else:
            warm = StreamingPoseEstimator(session, sensor_hw=SENSOR_HW)
            for _ in warm.run(window_chunks(2, 0, 1)):
                pass
            estimator = StreamingPoseEstimator(session, window_ms=WINDOW_US / 1000, start_us=0, sensor_hw=SENSOR_HW)
            timer.seconds = 0.0
            began = time.perf_counter()
            poses = sum(len(estimator.push(*chunk)) for chunk in big)
        wall = time.perf_counter() - began
        paths[label] = {"poses": poses, "ort_ms_per_pose": 1e3 * timer.seconds / poses,
                        "overhead_ms_per_pose": 1e3 * (wall - timer.seconds) / poses}
    session = StepSession(path, threads=threads)
    return {"model": str(path), "variant": session.meta.config.get("variant"),
            "quantization": (session.meta.quantization or {}).get("mode"), "threads": threads,
            "events_per_window": EVENTS_PER_WINDOW, "paths": paths}


# -- report -----------------------------------------------------------------------------------------

def markdown(report: dict) -> str:
    cfg = report["config"]
    lines = [
        "# Runtime sessions: I/O binding and many streams per session", "",
        f"Created {report['created']} on {report['machine'].get('cpu_model') or platform.machine()} "
        f"({report['machine'].get('cpu_count', '?')} CPUs, load average {report.get('load_average_at_start', '?')} "
        f"at the start; figures are medians of interleaved runs, compare within a table only); "
        f"ORT threads {cfg['threads']}. "
        "`python benchmarks/bench_runtime_sessions.py" + (" --int8 ..." if cfg.get("int8") else "") + "`.", "",
        "## 1. Per-step cost of each session kind", "",
        "Outside ORT = the step's wall time minus the time inside onnxruntime's run call, measured per step.", "",
        "| graph | state floats | kind | median step ms | median outside ORT us | p90 outside ORT us |",
        "|---|---|---|---|---|---|",
    ]
    for entry in report["session_overhead"]:
        for kind, row in entry["kinds"].items():
            lines.append(f"| {entry['variant']} | {entry['state_floats']} | {kind} | {row['median_step_ms']:.2f} | "
                         f"{row['median_outside_ort_us']:.0f} | {row['p90_outside_ort_us']:.0f} |")
    lines += ["", "## 2. Many streams, one session", "",
              f"~{EVENTS_PER_WINDOW} events per 20 ms window, one window of events per stream per call, grids "
              "staggered; `independent` = N StreamingPoseEstimators sharing the session (batch-1 steps). "
              "Latency = one call (windowing + LNES + step(s)); with few calls per row, p99 is close to the maximum.", "",
              "| graph | N | runner | poses/s | p50 call ms | p99 call ms | calls |", "|---|---|---|---|---|---|---|"]
    for row in report["streams"]["rows"]:
        lines.append(f"| {row['variant']} | {row['streams']} | {row['runner']} | {row['poses_per_s']:.1f} | "
                     f"{row['p50_call_ms']:.1f} | {row['p99_call_ms']:.1f} | {row['calls']} |")
    budget = report["budget"]
    lines += ["", "## 3. Runtime overhead budget", "",
              f"Graph: `{budget['variant']}` {budget['quantization'] or 'fp32 (no INT8 graph given)'}, "
              f"{budget['threads']} threads, ~{EVENTS_PER_WINDOW} events per window, 100,000-event chunks. "
              "Overhead = everything per pose except onnxruntime's run call.", "",
              "| path | ORT ms / pose | overhead ms / pose | overhead % of ORT step |", "|---|---|---|---|"]
    for label, row in budget["paths"].items():
        lines.append(f"| {label} | {row['ort_ms_per_pose']:.2f} | {row['overhead_ms_per_pose']:.2f} | "
                     f"{100 * row['overhead_ms_per_pose'] / row['ort_ms_per_pose']:.1f}% |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--int8", help="INT8 `small` graph from `e3dpsm quantize` for the budget")
    parser.add_argument("--graphs", help="folder with tiny.onnx / small.onnx / paper.onnx to use instead of exporting")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--overhead-steps", type=int, default=60)
    parser.add_argument("--stream-windows", type=int, default=8)
    parser.add_argument("--budget-windows", type=int, default=48)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "runtime_sessions.json"))
    args = parser.parse_args()
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        given = Path(args.graphs) if args.graphs else None
        graphs = {name: given / f"{name}.onnx" if given and (given / f"{name}.onnx").is_file()
                  else export_variant(name, Path(tmp)) for name in ("tiny", "small", "paper")}
        print("session overhead", flush=True)
        overhead = [bench_session_overhead(graphs[name], args.threads, args.overhead_steps) for name in ("tiny", "small")]
        print("many streams", flush=True)
        streams = bench_streams(graphs["small"], args.threads, args.stream_windows, ("numpy", "iobinding"))
        paper = bench_streams(graphs["paper"], args.threads, args.stream_windows, ("numpy",))
        streams["rows"] += paper["rows"]
        print("budget", flush=True)
        budget = bench_budget(Path(args.int8) if args.int8 else graphs["small"], args.threads, args.budget_windows)
    report = {
        "load_average_at_start": [round(v, 2) for v in os.getloadavg()],
        **report_header("bench_runtime_sessions", {k: v for k, v in vars(args).items() if k != "out"}),
        "shared_machine": True, "seconds": time.perf_counter() - began,
        "session_overhead": overhead, "streams": streams, "budget": budget,
    }
    write_json_atomic(args.out, report)
    write_text_atomic(Path(args.out).with_suffix(".md"), markdown(report))
    print(markdown(report))
    print(f"-> {args.out} ({report['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
