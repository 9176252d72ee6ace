"""Throughput of `e3dpsm.events.events_to_lnes` (events per second, one core).

    python benchmarks/bench_lnes.py [--repeats 21] [--out benchmarks/results/lnes.json]

Two window sizes: ~8,000 events (the paper's typical 20 ms window, supplementary) and 1M
events (a dense window). Events are uniform over the 640 x 480 sensor with sorted
timestamps; every event lies in the window, as in `prepare`, where windows are pre-sliced.
The figure is the median over repeats of events / wall time of one call.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # numpy's element-wise ops are single-threaded anyway

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from e3dpsm.events import events_to_lnes  # noqa: E402
from e3dpsm.utils.env import report_header  # noqa: E402
from e3dpsm.utils.io import write_json_atomic  # noqa: E402

WINDOW_US = 20_000
SIZES = (8_000, 1_000_000)
TARGET_EVENTS_PER_S = 20e6


def synthetic_window(n: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    return (
        rng.integers(0, 640, n).astype(np.int32), rng.integers(0, 480, n).astype(np.int32),
        np.sort(rng.integers(0, WINDOW_US, n)).astype(np.int64), rng.integers(0, 2, n).astype(np.uint8),
    )


def measure(n: int, repeats: int) -> dict[str, float]:
    x, y, t, p = synthetic_window(n)
    events_to_lnes(x, y, t, p, 0, WINDOW_US)  # warm-up: caches, page faults
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        events_to_lnes(x, y, t, p, 0, WINDOW_US)
        seconds.append(time.perf_counter() - start)
    median = statistics.median(seconds)
    return {
        "events": n, "repeats": repeats, "median_ms": median * 1e3, "min_ms": min(seconds) * 1e3,
        "events_per_s": n / median,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "lnes.json"))
    args = parser.parse_args()
    results = [measure(n, args.repeats) for n in SIZES]
    report = {
        **report_header("benchmarks/bench_lnes.py", {"repeats": args.repeats, "window_us": WINDOW_US,
                                                    "frame_hw": [192, 256], "sensor_hw": [480, 640]}),
        "target_events_per_s": TARGET_EVENTS_PER_S,
        "results": results,
        "meets_target": all(r["events_per_s"] >= TARGET_EVENTS_PER_S for r in results),
    }
    write_json_atomic(args.out, report)
    for r in results:
        print(f"events_to_lnes: {r['events']:>9,} events/window  {r['median_ms']:8.3f} ms  "
              f"{r['events_per_s'] / 1e6:7.1f} M events/s")
    print(f"target {TARGET_EVENTS_PER_S / 1e6:.0f} M events/s: {'met' if report['meets_target'] else 'NOT met'}"
          f" -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
