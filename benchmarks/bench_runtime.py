"""Streaming runtime benchmarks (writes benchmarks/results/runtime.json).

    python benchmarks/bench_runtime.py [--model STEP.onnx] [--long-steps 100000] [--threads 1]

1. Overhead: the runtime's own cost per window (chunk validation, buffering, windowing,
   LNES, feeds) against the step time of the graph, at ~8,000 events per 20 ms window
   (the paper's typical density), events pushed in chunks of 100,000. Target: overhead
   < 10% of the `small` INT8 graph's step. `--model` names the graph to compare with (an
   INT8 graph from `e3dpsm quantize`); without it the `small` fp32 graph is exported and
   used, and the absolute overhead in ms is reported so the ratio can be recomputed
   against any other graph's step time.
2. Endurance: `--long-steps` windows (default 100,000) of a synthetic stream through a
   `tiny` graph (exported at --long-hw, default 64 x 96, to fit the run in minutes on a
   shared CPU; the runtime code path is the same at any resolution), with random silent
   stretches (empty windows). Checks every pose is finite and samples the process RSS
   (psutil) at the start, middle and end: memory must stay flat.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator

import numpy as np
import psutil

from e3dpsm.runtime import StepSession, StreamingPoseEstimator
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import write_json_atomic

WINDOW_US = 20_000
SENSOR_HW = (480, 640)
CHUNK_EVENTS = 100_000
OVERHEAD_TARGET = 0.10


def export_variant(name: str, folder: Path, **overrides: int) -> Path:
    """An untrained graph of variant `name` (timing does not depend on the weights).

    Exported in a child process so this one never imports torch: the figures (RSS above
    all) are those of a process with numpy and onnxruntime only, as on a device.
    """
    suffix = "".join(f"_{k}{v}" for k, v in overrides.items())
    path = folder / f"{name}{suffix}.onnx"
    code = (
        "import torch, e3dpsm; from e3dpsm.export import export_step; torch.manual_seed(0); "
        f"export_step(e3dpsm.create_model({name!r}, **{overrides!r}).eval(), {str(path)!r})"
    )
    subprocess.run([sys.executable, "-c", code], check=True, stdout=subprocess.DEVNULL)
    return path


def synthetic_chunks(
    windows: int, events_per_window: float, seed: int, silent_fraction: float = 0.0,
) -> Iterator[tuple[np.ndarray, ...]]:
    """Chunks of ~CHUNK_EVENTS sorted events over windows [kT, (k+1)T), k = 0..windows,
    generated lazily so a long stream never sits in memory. Poisson counts per window; a
    window is silent with probability `silent_fraction`, except the first and last of each
    chunk (so window `windows`, one past the end, closes the last one)."""
    rng = np.random.default_rng(seed)
    per_chunk = max(1, int(CHUNK_EVENTS // max(events_per_window, 1)))
    for first in range(0, windows + 1, per_chunk):  # +1: one window past the end closes the last
        count = min(per_chunk, windows + 1 - first)
        n_per = rng.poisson(events_per_window, count)
        n_per[rng.random(count) < silent_fraction] = 0
        n_per[[0, -1]] = np.maximum(n_per[[0, -1]], 1)
        window_of = np.repeat(np.arange(first, first + count), n_per)
        t = window_of * WINDOW_US + rng.integers(0, WINDOW_US, window_of.size)
        t.sort()
        n = t.size
        # The canonical dtypes `read_events` returns, as `e3dpsm run` feeds them.
        yield (
            rng.integers(0, SENSOR_HW[1], n, dtype=np.int32), rng.integers(0, SENSOR_HW[0], n, dtype=np.int32),
            t.astype(np.int64), rng.integers(0, 2, n, dtype=np.uint8),
        )


def bench_overhead(model: Path, windows: int, threads: int) -> dict:
    session = StepSession(model, threads=threads)
    estimator = StreamingPoseEstimator(session, window_ms=WINDOW_US / 1000)
    warm = StreamingPoseEstimator(session)  # first runs allocate ORT arenas; not measured
    for _ in warm.run(synthetic_chunks(10, 8000, seed=1)):
        pass
    for _ in estimator.run(synthetic_chunks(windows, 8000, seed=0)):
        pass
    s = estimator.stats.to_dict()
    ratio = s["mean_overhead_ms"] / s["mean_step_ms"]
    return {
        "model": str(model), "variant": session.meta.config.get("variant"),
        "quantization": session.meta.quantization, "threads": threads, "windows": s["windows"],
        "events_per_window": s["events"] / s["windows"], "mean_step_ms": s["mean_step_ms"],
        "overhead_ms": s["mean_overhead_ms"], "overhead_fraction_of_step": ratio,
        "target_fraction": OVERHEAD_TARGET, "meets_target": ratio < OVERHEAD_TARGET,
    }


def bench_endurance(model: Path, steps: int, threads: int) -> dict:
    process = psutil.Process()
    # Grid anchored at 0 and an event in the window after the last: exactly `steps` windows.
    estimator = StreamingPoseEstimator(model, threads=threads, start_us=0)
    checkpoints = {"start": min(1_000, steps // 4), "middle": steps // 2}  # start: after warm-up
    rss_mb: dict[str, float] = {}
    max_abs_pose = 0.0
    nonfinite = 0
    began = time.perf_counter()
    for index, pose in enumerate(estimator.run(synthetic_chunks(steps, 300, seed=2, silent_fraction=0.05)), 1):
        finite = np.isfinite(pose.pose)
        nonfinite += int(not finite.all())
        max_abs_pose = max(max_abs_pose, float(np.abs(pose.pose).max()))
        for name, at in checkpoints.items():
            if index == at:
                rss_mb[name] = process.memory_info().rss / 2**20
    rss_mb["end"] = process.memory_info().rss / 2**20
    s = estimator.stats.to_dict()
    state_finite = all(np.isfinite(v).all() for v in estimator.state.values())
    return {
        "model": str(model), "variant": estimator.session.meta.config.get("variant"),
        "frame_hw": list(estimator.frame_hw), "threads": threads, "steps": s["windows"],
        "empty_windows": s["empty_windows"], "events": s["events"], "seconds": time.perf_counter() - began,
        "mean_step_ms": s["mean_step_ms"], "overhead_ms": s["mean_overhead_ms"],
        "all_poses_finite": nonfinite == 0, "nonfinite_poses": nonfinite, "final_state_finite": state_finite,
        "max_abs_pose_mm": max_abs_pose, "rss_mb": rss_mb, "torch_imported": "torch" in sys.modules,
        "rss_growth_mb": rss_mb.get("end", float("nan")) - rss_mb.get("start", float("nan")),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", help="graph for the overhead ratio (default: export small fp32)")
    parser.add_argument("--overhead-windows", type=int, default=200)
    parser.add_argument("--long-steps", type=int, default=100_000)
    parser.add_argument("--long-hw", type=int, nargs=2, default=(64, 96), metavar=("H", "W"))
    parser.add_argument("--threads", type=int, default=1, help="ORT intra-op threads (edge: 1)")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "runtime.json"))
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        model = Path(args.model) if args.model else export_variant("small", Path(tmp))
        overhead = bench_overhead(model, args.overhead_windows, args.threads)
        overhead["graph_note"] = ("given graph" if args.model else
                                  "small fp32 (no INT8 graph given): recompute the ratio from overhead_ms")
        print(f"overhead: {overhead['overhead_ms']:.2f} ms per window vs {overhead['mean_step_ms']:.2f} ms step "
              f"({overhead['overhead_fraction_of_step']:.1%}) on {overhead['variant']} [{overhead['graph_note']}]")
        tiny = export_variant("tiny", Path(tmp), height=args.long_hw[0], width=args.long_hw[1])
        endurance = bench_endurance(tiny, args.long_steps, args.threads)
    print(f"endurance: {endurance['steps']} steps in {endurance['seconds']:.0f} s, "
          f"finite={endurance['all_poses_finite']}, RSS MB {', '.join(f'{k} {v:.1f}' for k, v in endurance['rss_mb'].items())}")
    report = {
        **report_header("bench_runtime", {k: v for k, v in vars(args).items() if k != "out"}),
        "overhead": overhead, "endurance": endurance,
    }
    write_json_atomic(args.out, report)
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
