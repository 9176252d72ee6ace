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
from dataclasses import dataclass
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
                    total[name][k], runtime[name][k] = _phased_step(runner, frame, clock)
                else:
                    t0 = clock()
                    runner.step(frame)
                    total[name][k] = clock() - t0
                position[name] += 1
            if on_chunk is not None:
                on_chunk(min(chunk, steps - start))
    return {name: StepTimes(total[name], runtime.get(name)) for name in runners}


def _phased_step(runner: PhasedRunner, frame: np.ndarray, clock: Clock) -> tuple[float, float]:
    """(whole step, runtime's call) in seconds."""
    t0 = clock()
    runner.prepare(frame)
    t1 = clock()
    runner.run()
    t2 = clock()
    runner.collect()
    t3 = clock()
    return t3 - t0, t2 - t1
