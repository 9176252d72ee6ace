"""Streaming pose estimation: event chunks of any size in, timestamped poses out.

Numpy and onnxruntime only (no torch): this is what runs on an edge device.

Semantics (one stream):
- Windows are the regular grid [t0 + kT, t0 + (k+1)T), t0 = `start_us` or the first
  event's timestamp, cut with `e3dpsm.events.window_bounds` (the one definition shared with
  `prepare`), so a stream run here sees the same windows and LNES frames as training did.
- A window is emitted only once it is proven complete: by an event at or after its end
  (timestamps are non-decreasing, so nothing can fall into it later), by `flush(until_us)`
  (the caller vouches that no event before `until_us` is still to come), or by `finish()`
  at the end of the stream, which closes every window ending at or before the last event's
  microsecond (`window_bounds`' default end). The trailing partial window is dropped: its
  LNES would be normalised over time the stream never covered.
- An empty window (no events in it) is still one step of the model with an all-zero LNES
  frame: the S5 states decay by one window and the Kalman fusion predicts with the delta
  head and updates with the direct head, exactly as the model defines a quiet window. The
  estimate therefore keeps moving with the model's dynamics; it is not frozen or skipped,
  so the pose timestamps stay on the T grid and the state never skips time.
- Each pose is timestamped at its window's END (`t_us`): the model predicts the pose at
  the end of the window, and `prepare` aligns ground truth there too.
- Events earlier than an event already received (or than the start of the window being
  filled) raise `InputError`; each chunk goes through `validate_events` (NaN/inf,
  out-of-range coordinates, unsorted timestamps, polarity; -1/+1 is converted to 0/1).
  Events before an explicit `start_us` are skipped and counted.

The state carries a batch axis (StateSpec layout from the graph metadata); this class
drives a batch of one. Several streams batched through one session, each with its own
`EventWindower` and state row, are `MultiStreamEstimator` (e3dpsm.runtime.multistream).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np

from e3dpsm.errors import InputError
from e3dpsm.events import events_to_lnes, validate_events, window_bounds, window_us_from_ms
from e3dpsm.runtime.stepping import StateArrays, StreamStepper, open_stepper
from e3dpsm.utils.stats import LogHistogram

EventChunk = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # x, y, t_us, p


@dataclass(frozen=True)
class PoseEstimate:
    """The model's outputs for one window [t_start_us, t_us); poses in mm, camera frame."""

    t_us: int  # window end: the time the pose refers to
    t_start_us: int
    events: int  # events in the window (0 for an empty window)
    outputs: dict[str, np.ndarray]  # "pose" (fused), "pose_direct", "pose_delta": float32 [J, 3]
    lnes: np.ndarray | None = None  # the window's LNES frame [2, H, W], only with keep_frames=True

    @property
    def pose(self) -> np.ndarray:
        return self.outputs["pose"]


@dataclass
class StreamStats:
    """Counters and timings since the estimator was created (or reset)."""

    windows: int = 0
    empty_windows: int = 0
    events: int = 0  # events that fell into emitted windows
    events_received: int = 0
    events_before_start: int = 0
    step_seconds: float = 0.0  # inside onnxruntime
    overhead_seconds: float = 0.0  # validation, buffering, windowing and LNES: the runtime's own cost
    # Per window, in fixed memory however long the stream: inside onnxruntime, and the whole
    # window (LNES, feeds and the step; not the cutting of chunks into windows, shared by many).
    # Empty (and left out of to_dict) where windows are stepped in batches (multistream.py).
    step_ms: LogHistogram = field(default_factory=LogHistogram)
    window_ms: LogHistogram = field(default_factory=LogHistogram)

    def to_dict(self) -> dict[str, float | int | dict]:
        per_window = 1e3 / self.windows if self.windows else float("nan")
        return {
            "windows": self.windows, "empty_windows": self.empty_windows, "events": self.events,
            "events_received": self.events_received, "events_before_start": self.events_before_start,
            "mean_step_ms": self.step_seconds * per_window, "mean_overhead_ms": self.overhead_seconds * per_window,
            "step_seconds": self.step_seconds, "overhead_seconds": self.overhead_seconds,
            **({"step_ms": self.step_ms.summary(), "window_ms": self.window_ms.summary()}
               if self.step_ms.count else {}),
        }


class EventWindower:
    """Cuts one event stream, pushed in chunks, into complete T-us windows (numpy only).

    `push` returns the windows the chunk completed as (start_us, x, y, t_us, p) with the
    window's events; pending events are held as a list of chunks and joined only when a
    window completes, so pushing many tiny chunks stays linear in the number of events.
    """

    def __init__(self, window_us: int, sensor_hw: tuple[int, int], start_us: int | None = None) -> None:
        if window_us <= 0:
            raise InputError(f"window length must be positive, got {window_us} us")
        self.window_us = int(window_us)
        self.sensor_hw = (int(sensor_hw[0]), int(sensor_hw[1]))
        self.explicit_start = start_us is not None
        self.next_start_us: int | None = None if start_us is None else int(start_us)
        self.last_t_us: int | None = None  # newest event timestamp received
        self.first_event_us: int | None = None
        self.skipped_before_start = 0
        # Earliest timestamp still acceptable: the latest event, or the start of the window
        # being filled once windows were closed (a flush may close time no event reached).
        self._floor_us: int | None = None
        self._pending: list[EventChunk] = []
        self._pending_count = 0

    @property
    def pending_events(self) -> int:
        return self._pending_count

    def push(self, x: np.ndarray, y: np.ndarray, t_us: np.ndarray, p: np.ndarray) -> list[tuple[int, EventChunk]]:
        x, y, t, p = validate_events(x, y, t_us, p, self.sensor_hw)
        if t.size == 0:
            return []
        if self._floor_us is not None and t[0] < self._floor_us:
            raise InputError(
                f"events out of order across chunks: a chunk starts at t = {int(t[0])} us, before "
                f"{self._floor_us} us (the latest event, or the start of the window being filled); "
                "the stream must be sorted by time"
            )
        if self.first_event_us is None:
            self.first_event_us = int(t[0])
        self.last_t_us = int(t[-1])
        self._floor_us = self.last_t_us  # >= the old floor: the chunk passed the check above
        if self.next_start_us is None:
            self.next_start_us = int(t[0])
        if self.explicit_start and t[0] < self.next_start_us:
            keep = int(np.searchsorted(t, self.next_start_us, side="left"))
            self.skipped_before_start += keep
            x, y, t, p = x[keep:], y[keep:], t[keep:], p[keep:]
        if t.size:
            self._pending.append((x, y, t, p))
            self._pending_count += t.size
        # An event at time t proves every window ending at or before t complete.
        return self._cut(self.last_t_us)

    def flush(self, until_us: int) -> list[tuple[int, EventChunk]]:
        """Close every window ending at or before `until_us` (no earlier event is to come)."""
        if self.next_start_us is None:
            raise InputError("flush before any event: the window grid starts at the first event (or start_us)")
        return self._cut(int(until_us))

    def finish(self) -> list[tuple[int, EventChunk]]:
        """End of stream: close windows up to the last event's microsecond; drop the partial rest."""
        if self.last_t_us is None or self.next_start_us is None:
            return []
        return self._cut(self.last_t_us + 1)

    def _cut(self, end_us: int) -> list[tuple[int, EventChunk]]:
        assert self.next_start_us is not None  # set by the first push or start_us
        if end_us < self.next_start_us + self.window_us:
            return []
        x, y, t, p = self._joined()
        starts, ranges = window_bounds(t, self.window_us, self.next_start_us, end_us)
        windows = [
            (start, (x[lo:hi], y[lo:hi], t[lo:hi], p[lo:hi]))
            for start, (lo, hi) in zip(starts.tolist(), ranges.tolist())
        ]
        rest = int(ranges[-1, 1])
        self.next_start_us = int(starts[-1]) + self.window_us
        self._floor_us = self.next_start_us if self._floor_us is None else max(self._floor_us, self.next_start_us)
        self._pending = [(x[rest:], y[rest:], t[rest:], p[rest:])] if rest < t.size else []
        self._pending_count = t.size - rest
        return windows

    def _joined(self) -> EventChunk:
        if not self._pending:
            empty = (np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros(0, np.uint8))
            return empty
        if len(self._pending) == 1:
            return self._pending[0]
        joined = tuple(np.concatenate(column) for column in zip(*self._pending))
        self._pending = [joined]  # type: ignore[list-item]
        return joined  # type: ignore[return-value]


class StreamingPoseEstimator:
    """Events in (chunks of any size), poses out, recurrent states carried between windows.

        est = StreamingPoseEstimator("step.onnx", window_ms=20)
        for x, y, t, p in chunks:
            for pose in est.push(x, y, t, p):
                use(pose.t_us, pose.pose)
        for pose in est.finish():
            ...

    `push`, `flush` and `finish` return lists (not lazy generators), so the state advances
    whether or not the caller iterates; a chunk that fails validation raises before anything
    changes, so the estimator stays usable. A long silence costs one step per window (module
    doc). `window_ms` defaults to the graph's training window, `sensor_hw` to the graph
    metadata's; `threads` applies only when `model` is a path.
    """

    def __init__(
        self,
        model: StreamStepper | str | os.PathLike,
        *,
        window_ms: float | None = None,
        start_us: int | None = None,
        sensor_hw: tuple[int, int] | None = None,
        threads: int | None = None,
        keep_frames: bool = False,
    ) -> None:
        self.session = open_stepper(model, threads=threads) if isinstance(model, (str, os.PathLike)) else model
        meta = self.session.meta
        self.window_ms = float(window_ms if window_ms is not None else meta.train_window_ms)
        self.window_us = window_us_from_ms(self.window_ms)
        self.frame_hw = meta.frame_hw
        if sensor_hw is None:
            if "sensor_hw" not in meta.frame_input:
                raise InputError(
                    f"{self.session.path}: metadata gives no sensor_hw for the frame input; pass sensor_hw"
                )
            sensor_hw = tuple(meta.frame_input["sensor_hw"])  # type: ignore[assignment]
        self.sensor_hw = (int(sensor_hw[0]), int(sensor_hw[1]))
        self.joints: list[str] = list(meta.joints)
        self._start_us = start_us
        self.keep_frames = keep_frames  # PoseEstimate.lnes for rendering (`e3dpsm run --render`)
        self.reset()

    def reset(self) -> None:
        """Forget the stream: fresh states, a new window grid, zeroed statistics."""
        self.windower = EventWindower(self.window_us, self.sensor_hw, self._start_us)
        self.state: StateArrays = self.session.init_state(1)
        self.stats = StreamStats()
        self._window_feed = np.full(1, self.window_ms, dtype=np.float32)

    @property
    def first_window_start_us(self) -> int | None:
        """Start of window 0 of the grid (None until the first event, without start_us)."""
        return self._start_us if self._start_us is not None else self.windower.first_event_us

    def push(self, x: np.ndarray, y: np.ndarray, t_us: np.ndarray, p: np.ndarray) -> list[PoseEstimate]:
        """Add a chunk of events; returns the poses of the windows it completed."""
        began = time.perf_counter()
        windows = self.windower.push(x, y, t_us, p)
        self.stats.events_received += int(np.asarray(t_us).shape[0])
        self.stats.events_before_start = self.windower.skipped_before_start
        return self._run(windows, began)

    def flush(self, until_us: int) -> list[PoseEstimate]:
        """Emit every window ending at or before `until_us`; events before it must all be in."""
        began = time.perf_counter()
        return self._run(self.windower.flush(until_us), began)

    def finish(self) -> list[PoseEstimate]:
        """End of stream: emit the remaining complete windows (module doc)."""
        began = time.perf_counter()
        return self._run(self.windower.finish(), began)

    def run(self, chunks: Iterable[EventChunk]) -> Iterator[PoseEstimate]:
        """Every pose of a stream given as an iterable of (x, y, t_us, p) chunks, then `finish`."""
        for chunk in chunks:
            yield from self.push(*chunk)
        yield from self.finish()

    def _run(self, windows: list[tuple[int, EventChunk]], began: float) -> list[PoseEstimate]:
        poses = []
        step_seconds = 0.0
        for start_us, events in windows:
            pose, seconds = self._step(start_us, events)
            poses.append(pose)
            step_seconds += seconds
        self.stats.step_seconds += step_seconds
        self.stats.overhead_seconds += time.perf_counter() - began - step_seconds
        return poses

    def _step(self, start_us: int, events: EventChunk) -> tuple[PoseEstimate, float]:
        """One window through the graph; also returns the seconds spent inside onnxruntime."""
        window_began = time.perf_counter()
        x, y, t, p = events
        frame = events_to_lnes(x, y, t, p, start_us, self.window_us, *self.frame_hw, self.sensor_hw)
        feeds = self.session.feeds(frame[np.newaxis], self.state, self._window_feed)
        began = time.perf_counter()
        outputs, self.state = self.session.run_feeds(feeds)
        done = time.perf_counter()
        seconds = done - began
        self.stats.step_ms.add(seconds * 1e3)
        self.stats.window_ms.add((done - window_began) * 1e3)
        self.stats.windows += 1
        self.stats.empty_windows += int(t.size == 0)
        self.stats.events += int(t.size)
        return PoseEstimate(
            t_us=start_us + self.window_us, t_start_us=start_us, events=int(t.size),
            outputs={name: value[0] for name, value in outputs.items()},
            lnes=frame if self.keep_frames else None,
        ), seconds
