"""Step latency of graphs timed side by side: the quantiser's verdict.

A `StepTimer` takes {label: graph path} and returns {label: p50 step milliseconds}. The
default one runs every graph on the same held-out frames, states carried, at the same
thread count, taking turns in short chunks of steps (interleaved, so load from elsewhere on
a shared machine hits every candidate alike) after a few warm-up steps, and reports the
medians. Tests inject their own timer to make the choice deterministic.

`SideBySideTimer.compare` times one graph against a reference for longer and says how sure
the speed-up is (`speedup_interval`): on a shared 2-core AVX-512 VNNI host (2026-12-02) eight
30-step timings of one INT8 graph against fp32 gave 0.56-1.25x (sd 0.22), eight 100-step
ones 0.82-1.03x (sd 0.065), so a verdict read off 30 steps was a coin toss there.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from typing import Callable, Mapping

import numpy as np

from e3dpsm.runtime.session import CarriedStateRunner

StepTimer = Callable[[Mapping[str, "os.PathLike | str"]], Mapping[str, float]]
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
    """The speed-up of `candidate_s` over `reference_s` (per-step times in step order, timed
    side by side in rounds of `chunk` steps each, as measure_side_by_side does) and a
    bootstrap interval over rounds: rounds are drawn with replacement, the same rounds of
    both graphs together (load from elsewhere hits a round of both), and the speed-up of
    each draw's medians taken; the interval spans the central `coverage` of them."""
    candidate_s, reference_s = np.asarray(candidate_s, float), np.asarray(reference_s, float)
    if candidate_s.shape != reference_s.shape or candidate_s.size == 0 or chunk < 1:
        raise ValueError("speedup_interval needs two equally long, non-empty timings and chunk >= 1")
    speedup = float(np.median(reference_s) / np.median(candidate_s))
    starts = np.arange(0, candidate_s.size, chunk)
    rounds = [(candidate_s[i:i + chunk], reference_s[i:i + chunk]) for i in starts]
    rng = np.random.default_rng(seed)
    draws = np.empty(resamples)
    for k in range(resamples):
        picked = rng.integers(0, len(rounds), len(rounds))
        draws[k] = (np.median(np.concatenate([rounds[i][1] for i in picked]))
                    / np.median(np.concatenate([rounds[i][0] for i in picked])))
    tail = 50 * (1 - coverage)
    low, high = np.percentile(draws, [tail, 100 - tail])
    return SpeedupInterval(speedup, float(low), float(high), coverage, len(rounds))


class SideBySideTimer:
    """Interleaved median step latency (ms) of several graphs on the same frames.

    `steps` timed steps per graph after `warmup` untimed ones, in rounds of `chunk` steps
    per graph. Kept small on purpose: the search times a handful of candidates once, and
    the ranking it needs (which within-budget graph is fastest) is coarse.
    """

    def __init__(self, frames: np.ndarray, window_ms: float, threads: int | None = None, *,
                 steps: int = 30, warmup: int = 5, chunk: int = 10, runtime: str = "onnxruntime") -> None:
        if len(frames) == 0:
            raise ValueError("the timer needs at least one frame")
        self.frames = np.asarray(frames, dtype=np.float32)
        self.window_ms, self.threads, self.runtime = window_ms, threads, runtime
        self.steps, self.warmup, self.chunk = steps, warmup, chunk

    def __call__(self, graphs: Mapping[str, os.PathLike | str]) -> dict[str, float]:
        return {label: 1e3 * float(np.median(t)) for label, t in self._seconds(graphs, self.steps).items()}

    def compare(self, graph: os.PathLike | str, reference: os.PathLike | str, steps: int) -> dict:
        """`graph` timed beside `reference` over `steps` steps: both p50s (ms), the speed-up and
        its interval (speedup_interval)."""
        seconds = self._seconds({"graph": graph, "reference": reference}, steps)
        interval = speedup_interval(seconds["graph"], seconds["reference"], self.chunk)
        return {"p50_ms": 1e3 * float(np.median(seconds["graph"])),
                "fp32_p50_ms": 1e3 * float(np.median(seconds["reference"])),
                "speedup_vs_fp32": interval.speedup, "interval": interval.to_dict(),
                "timer": {**self.describe(), "steps": steps}}

    def _seconds(self, graphs: Mapping[str, os.PathLike | str], steps: int) -> dict[str, np.ndarray]:
        """Per-step seconds of each graph, in step order (measure_side_by_side)."""
        from e3dpsm.profiles.latency import measure_side_by_side
        from e3dpsm.quantize.holdout import open_stepper

        runners = {label: CarriedStateRunner(open_stepper(path, self.runtime, self.threads), self.window_ms)
                   for label, path in graphs.items()}
        return measure_side_by_side(runners, self.frames, steps, self.warmup, chunk=self.chunk)

    def describe(self) -> dict:
        return {"kind": "side_by_side", "runtime": self.runtime, "threads": self.threads, "steps": self.steps, "warmup": self.warmup,
                "chunk": self.chunk, "frames": int(len(self.frames))}
