"""Step times measured side by side, split into the runtime's own call and the Python around it.

A runner that has the three phases of a step (`prepare(lnes)`: feeds built and checked;
`run()`: the runtime's own call and nothing else; `collect()`: outputs copied out, states
handed over) is timed phase by phase, so its step's Python overhead (total minus the run)
is measured apart from the runtime, the part an outside tool such as OpenVINO's
`benchmark_app` times. A runner with only `step(lnes)` gets its total.

Fairness, as in every side-by-side figure of the project: every runner sees the same frames
in the same order with its own states carried, and the runners take turns in chunks of
steps, so a burst of load from elsewhere on a shared machine hits all of them.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Mapping, Protocol, runtime_checkable

import numpy as np

Clock = Callable[[], float]  # seconds, monotonic (time.perf_counter; tests inject their own)


class StepRunner(Protocol):
    def reset(self) -> None: ...
    def step(self, lnes: np.ndarray) -> None: ...


@runtime_checkable
class PhasedRunner(Protocol):
    """`step` = `prepare`, `run`, `collect`; `run` is the runtime's call alone."""

    def reset(self) -> None: ...
    def step(self, lnes: np.ndarray) -> None: ...
    def prepare(self, lnes: np.ndarray) -> None: ...
    def run(self) -> None: ...
    def collect(self) -> None: ...


@dataclass(frozen=True)
class StepTimes:
    """Seconds per timed step: the whole step, and (phased runners) the runtime's call."""

    total: np.ndarray
    runtime: np.ndarray | None = None

    @property
    def overhead(self) -> np.ndarray | None:
        """Per step: feeds, state hand-over and output copies (total minus the runtime's call)."""
        return None if self.runtime is None else self.total - self.runtime


def time_side_by_side(runners: Mapping[str, Any], frames: np.ndarray, steps: int, warmup: int,
                      chunk: int = 25, on_chunk: Callable[[int], None] | None = None,
                      clock: Clock = time.perf_counter) -> dict[str, StepTimes]:
    """`warmup` untimed steps per runner, then `steps` timed steps in rounds of `chunk` steps
    per runner. Step k of a runner uses frame k (mod the frame count), warm-up included.
    `on_chunk(n)` is called after every n timed steps of a runner (progress bars)."""
    for runner in runners.values():
        runner.reset()
        for k in range(warmup):
            runner.step(frames[k % len(frames)][None])
    total = {name: np.empty(steps) for name in runners}
    runtime = {name: np.empty(steps) for name, runner in runners.items() if isinstance(runner, PhasedRunner)}
    position = {name: warmup for name in runners}
    for start in range(0, steps, chunk):
        for name, runner in runners.items():
            for k in range(start, min(start + chunk, steps)):
                frame = frames[position[name] % len(frames)][None]
                if name in runtime:
                    total[name][k], runtime[name][k] = phased_step(runner, frame, clock)
                else:
                    t0 = clock()
                    runner.step(frame)
                    total[name][k] = clock() - t0
                position[name] += 1
            if on_chunk is not None:
                on_chunk(min(chunk, steps - start))
    return {name: StepTimes(total[name], runtime.get(name)) for name in runners}


def phased_step(runner: PhasedRunner, frame: np.ndarray, clock: Clock) -> tuple[float, float]:
    """(whole step, runtime's call) in seconds."""
    t0 = clock()
    runner.prepare(frame)
    t1 = clock()
    runner.run()
    t2 = clock()
    runner.collect()
    t3 = clock()
    return t3 - t0, t2 - t1


# The share of bootstrap speed-ups an interval spans (10th to 90th percentile).
INTERVAL_COVERAGE = 0.8


@dataclass(frozen=True)
class SpeedupInterval:
    """A speed-up (reference p50 / candidate p50) and the range its timing supports."""

    speedup: float
    low: float
    high: float
    coverage: float
    rounds: int

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def speedup_interval(candidate_s: np.ndarray, reference_s: np.ndarray, chunk: int, *, resamples: int = 1000,
                     coverage: float = INTERVAL_COVERAGE, seed: int = 0) -> SpeedupInterval:
    """The speed-up of `candidate_s` over `reference_s` (per-step seconds in step order, timed
    side by side in rounds of `chunk` steps) and a bootstrap interval over rounds: rounds drawn
    with replacement, the same rounds of both together (load from elsewhere hits a round of
    both), the speed-up of each draw's medians; the interval spans their central `coverage`.

    Why an interval: on a shared 2-core AVX-512 VNNI host (2026-12-02) eight 30-step timings of
    one INT8 graph against fp32 gave 0.56-1.25x, eight 100-step ones 0.82-1.03x."""
    rounds = _paired_rounds(candidate_s, reference_s, chunk, "speedup_interval")
    speedup = float(np.median(np.asarray(reference_s, float)) / np.median(np.asarray(candidate_s, float)))
    rng = np.random.default_rng(seed)
    draws = np.empty(resamples)
    for k in range(resamples):
        picked = rng.integers(0, len(rounds), len(rounds))
        draws[k] = (np.median(np.concatenate([rounds[i][1] for i in picked]))
                    / np.median(np.concatenate([rounds[i][0] for i in picked])))
    tail = 50 * (1 - coverage)
    low, high = np.percentile(draws, [tail, 100 - tail])
    return SpeedupInterval(speedup, float(low), float(high), coverage, len(rounds))


def turn_paired_speedup(candidate_s: np.ndarray, reference_s: np.ndarray, chunk: int) -> float:
    """The speed-up of `candidate_s` over `reference_s` (per-step times in step order, timed
    side by side in rounds of `chunk` steps) as the median over rounds of each round's
    reference median over its candidate median: drift slower than a round cancels within
    each round's pair. Why not the ratio of whole-run medians: on the 2-core VNNI host
    (2026-12-04) one graph's median jumped from 28 to 39 ms for tens of seconds at a time, and
    the ratio of two runs' medians moved by up to 1.3x with which of them the jumps hit."""
    rounds = _paired_rounds(candidate_s, reference_s, chunk, "turn_paired_speedup")
    return float(np.median([np.median(reference) / np.median(candidate) for candidate, reference in rounds]))


def _paired_rounds(candidate_s: np.ndarray, reference_s: np.ndarray, chunk: int,
                   caller: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(candidate, reference) seconds of each side-by-side round of `chunk` steps."""
    candidate_s, reference_s = np.asarray(candidate_s, float), np.asarray(reference_s, float)
    if candidate_s.shape != reference_s.shape or candidate_s.size == 0 or chunk < 1:
        raise ValueError(f"{caller} needs two equally long, non-empty timings and chunk >= 1")
    return [(candidate_s[i:i + chunk], reference_s[i:i + chunk]) for i in range(0, candidate_s.size, chunk)]


def time_beside(candidate: Any, reference: Any, frames: np.ndarray, steps: int, *, warmup: int = 5,
                chunk: int = 10, clock: Clock = time.perf_counter) -> dict[str, Any]:
    """Two step runners timed side by side on the same frames: both p50s (ms), the speed-up of
    `candidate` over `reference` and its interval (speedup_interval)."""
    if len(frames) == 0:
        raise ValueError("timing needs at least one frame")
    times = time_side_by_side({"candidate": candidate, "reference": reference}, frames, steps, warmup, chunk,
                              clock=clock)
    seconds = {name: t.total for name, t in times.items()}
    interval = speedup_interval(seconds["candidate"], seconds["reference"], chunk)
    return {"p50_ms": 1e3 * float(np.median(seconds["candidate"])),
            "fp32_p50_ms": 1e3 * float(np.median(seconds["reference"])),
            "speedup_vs_fp32": interval.speedup, "interval": interval.to_dict(),
            "timer": {"kind": "side_by_side", "steps": steps, "warmup": warmup, "chunk": chunk,
                      "frames": int(len(frames))}}
