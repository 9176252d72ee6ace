"""Step latency of candidate graphs for the latency-aware exclusion search.

A `StepTimer` takes {label: graph path} and returns {label: p50 step milliseconds}. The
default one runs every graph on the same held-out frames, states carried, at the same
thread count, taking turns in short chunks of steps (interleaved, so load from elsewhere on
a shared machine hits every candidate alike) after a few warm-up steps, and reports the
medians. Tests inject their own timer to make the choice deterministic.
"""
from __future__ import annotations

import os
from typing import Callable, Mapping

import numpy as np

from e3dpsm.runtime.session import CarriedStateRunner, StepSession

StepTimer = Callable[[Mapping[str, "os.PathLike | str"]], Mapping[str, float]]


class SideBySideTimer:
    """Interleaved median step latency (ms) of several graphs on the same frames.

    `steps` timed steps per graph after `warmup` untimed ones, in rounds of `chunk` steps
    per graph. Kept small on purpose: the search times a handful of candidates once, and
    the ranking it needs (which within-budget graph is fastest) is coarse.
    """

    def __init__(self, frames: np.ndarray, window_ms: float, threads: int | None = None, *,
                 steps: int = 30, warmup: int = 5, chunk: int = 10) -> None:
        if len(frames) == 0:
            raise ValueError("the timer needs at least one frame")
        self.frames = np.asarray(frames, dtype=np.float32)
        self.window_ms, self.threads = window_ms, threads
        self.steps, self.warmup, self.chunk = steps, warmup, chunk

    def __call__(self, graphs: Mapping[str, os.PathLike | str]) -> dict[str, float]:
        from e3dpsm.profiles.latency import measure_side_by_side

        runners = {label: CarriedStateRunner(StepSession(path, threads=self.threads), self.window_ms)
                   for label, path in graphs.items()}
        seconds = measure_side_by_side(runners, self.frames, self.steps, self.warmup, chunk=self.chunk)
        return {label: 1e3 * float(np.median(t)) for label, t in seconds.items()}

    def describe(self) -> dict:
        return {"kind": "side_by_side", "threads": self.threads, "steps": self.steps, "warmup": self.warmup,
                "chunk": self.chunk, "frames": int(len(self.frames))}
