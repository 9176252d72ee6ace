"""State-aware calibration data for INT8 static quantisation of the step graph.

ONNX Runtime's calibrator feeds each sample through the graph once; it never feeds the
recurrent states back. A recurrent step graph calibrated with zero states sees activations
a running stream never produces (an uninitialised Kalman filter, empty S5 memories). So
the samples are recorded from continuous FP32 rollouts of real sequences: every calibration
frame is paired with the states the FP32 graph carried into that frame, never reset.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np
from onnxruntime.quantization import CalibrationDataReader

from e3dpsm.data.prepared import PreparedSequence
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.runtime import StepSession

MIN_CALIBRATION_FRAMES = 16
StateSource = Literal["rollout", "zeros"]
STATE_SOURCES: tuple[str, ...] = ("rollout", "zeros")


@dataclass
class CalibrationSet:
    """One ORT feed dict per calibration frame (batch 1), and where the frames came from."""

    feeds: list[dict[str, np.ndarray]]
    state_source: str
    frames: dict[str, list[int]] = field(default_factory=dict)  # sequence -> frame indices
    seconds: float = 0.0

    def __len__(self) -> int:
        return len(self.feeds)


class FeedListReader(CalibrationDataReader):
    """Hands the calibrator a fixed list of feed dicts; `rewind` replays them."""

    def __init__(self, feeds: Sequence[dict[str, np.ndarray]]) -> None:
        self._feeds = list(feeds)
        self._next = 0

    def get_next(self) -> dict[str, np.ndarray] | None:
        if self._next >= len(self._feeds):
            return None
        self._next += 1
        return self._feeds[self._next - 1]

    def rewind(self) -> None:
        self._next = 0

    def __len__(self) -> int:
        return len(self._feeds)


def frame_plan(sequences: Sequence[PreparedSequence], frames: int) -> dict[str, list[int]]:
    """Spread `frames` calibration frames evenly over the sequences and over each sequence
    (from its first frame on, so stream starts are represented too)."""
    total = sum(s.frames for s in sequences)
    if frames < MIN_CALIBRATION_FRAMES:
        raise ConfigError(f"--frames {frames} is too few for calibration; use at least {MIN_CALIBRATION_FRAMES}")
    if total < MIN_CALIBRATION_FRAMES:
        raise DataError(
            f"the calibration split holds only {total} frames; at least {MIN_CALIBRATION_FRAMES} are needed"
        )
    frames = min(frames, total)
    plan: dict[str, list[int]] = {}
    left = frames
    for i, seq in enumerate(sequences):
        quota = min(seq.frames, math.ceil(left / (len(sequences) - i)))
        stride = max(1, seq.frames // quota)
        plan[seq.name] = list(range(0, seq.frames, stride))[:quota]
        left -= len(plan[seq.name])
    return plan


def record_calibration_set(
    fp32_model: str | os.PathLike, sequences: Sequence[PreparedSequence], frames: int, window_ms: float,
    *, state_source: StateSource = "rollout", threads: int | None = None,
) -> CalibrationSet:
    """Calibration feeds for `frames` frames of `sequences`.

    `state_source="rollout"` (the default, and the right one) pairs each frame with the
    states of a continuous FP32 rollout up to it; "zeros" (initial states, what ONNX
    Runtime's calibrator alone would see) exists to measure what that buys.
    """
    if state_source not in STATE_SOURCES:
        raise ConfigError(f"unknown state source {state_source!r}; choose from {list(STATE_SOURCES)}")
    started = time.perf_counter()
    session = StepSession(fp32_model, threads=threads)
    plan = frame_plan(sequences, frames)
    feeds: list[dict[str, np.ndarray]] = []
    for seq in sequences:
        wanted = set(plan[seq.name])
        if not wanted:
            continue
        state = session.init_state(1)
        for f in range(max(wanted) + 1):
            lnes = np.asarray(seq.lnes[f : f + 1], dtype=np.float32)
            if f in wanted:
                feeds.append(session.feeds(lnes, state if state_source == "rollout" else session.init_state(1),
                                           window_ms))
            if state_source == "rollout" and f < max(wanted):
                _, state = session.step(lnes, state, window_ms)
    return CalibrationSet(feeds, state_source, plan, time.perf_counter() - started)
