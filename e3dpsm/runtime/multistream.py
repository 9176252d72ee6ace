"""Many independent event streams through one step session, batched along the graph's batch axis.

Each stream behaves exactly as one `StreamingPoseEstimator` (see e3dpsm.runtime.stream for
the window grid, completeness, empty-window and ordering rules): it has its own
`EventWindower` (own start, window length and sensor size) and its own recurrent state,
which is one row of a shared state pool. Streams join (`add_stream`: the row starts from
the graph's initial state) and leave (`remove_stream`: the row is dropped) at any time.

Windows of different streams complete at different times. Every call first cuts the
complete windows of the streams it concerns into per-stream queues, then steps the queues
in rounds: round r runs, in one batched session call, the r-th queued window of every
stream that has one (gather their state rows, step, scatter back), so a stream's windows
stay in order and a stream without a complete window is not stepped. Each row carries its
own window length (the graph's window input has the batch axis).

State rows live in a pool [capacity, ...] per state; the state a batched step returns is
kept as it is (numpy arrays, or the `DeviceState` of an `IOBindingStepSession`) as long as
the next step runs the same rows, so a steady set of streams costs no gather / scatter.

Server use:

    est = MultiStreamEstimator("step.onnx")
    est.add_stream("cam0"); est.add_stream("cam1", start_us=0, window_ms=10)
    poses = est.push_many({"cam0": (x, y, t, p), "cam1": (x1, y1, t1, p1)})  # {id: [PoseEstimate]}
    est.remove_stream("cam1")
"""
from __future__ import annotations

import os
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Hashable, Iterable, Mapping

import numpy as np

from e3dpsm.errors import InputError
from e3dpsm.events import events_to_lnes, window_us_from_ms
from e3dpsm.runtime.stepping import StreamStepper, open_stepper
from e3dpsm.runtime.stream import EventChunk, EventWindower, PoseEstimate, StreamStats

StreamId = Hashable


@dataclass
class _Stream:
    windower: EventWindower
    window_ms: float
    window_us: int
    sensor_hw: tuple[int, int]
    start_us: int | None
    row: int
    ready: deque = field(default_factory=deque)  # (start_us, events) cut but not yet stepped
    stats: StreamStats = field(default_factory=StreamStats)


@dataclass
class MultiStreamStats:
    """Totals over all streams since the estimator was created."""

    session_calls: int = 0
    rows_stepped: int = 0
    step_seconds: float = 0.0  # inside the session
    overhead_seconds: float = 0.0  # everything else: validation, windowing, LNES, gather / scatter

    def to_dict(self) -> dict[str, float | int]:
        per_row = 1e3 / self.rows_stepped if self.rows_stepped else float("nan")
        return {
            "session_calls": self.session_calls, "rows_stepped": self.rows_stepped,
            "mean_batch": self.rows_stepped / self.session_calls if self.session_calls else float("nan"),
            "step_seconds": self.step_seconds, "overhead_seconds": self.overhead_seconds,
            "mean_step_ms_per_pose": self.step_seconds * per_row,
            "mean_overhead_ms_per_pose": self.overhead_seconds * per_row,
        }


class MultiStreamEstimator:
    """N event streams, one session (module doc). `window_ms` and `sensor_hw` are the
    defaults for streams that do not give their own; `max_batch` caps the rows of one call."""

    def __init__(
        self,
        model: StreamStepper | str | os.PathLike,
        *,
        window_ms: float | None = None,
        sensor_hw: tuple[int, int] | None = None,
        threads: int | None = None,
        max_batch: int | None = None,
    ) -> None:
        self.session = open_stepper(model, threads=threads) if isinstance(model, (str, os.PathLike)) else model
        meta = self.session.meta
        self.window_ms = float(window_ms if window_ms is not None else meta.train_window_ms)
        window_us_from_ms(self.window_ms)  # reject a bad default now, not at the first add_stream
        if sensor_hw is None and "sensor_hw" in meta.frame_input:
            sensor_hw = tuple(meta.frame_input["sensor_hw"])  # type: ignore[assignment]
        self.sensor_hw = None if sensor_hw is None else (int(sensor_hw[0]), int(sensor_hw[1]))
        if max_batch is not None and max_batch <= 0:
            raise InputError(f"max_batch must be positive, got {max_batch}")
        self.max_batch = max_batch
        self.frame_hw = meta.frame_hw
        self.joints: list[str] = list(meta.joints)
        self.stats = MultiStreamStats()
        self._streams: dict[StreamId, _Stream] = {}
        self._row_ids: list[StreamId] = []  # row -> stream id; rows 0..n-1 are in use
        self._pool: dict[str, np.ndarray] = {s.name: np.zeros((0, *s.shape), np.float32) for s in meta.states}
        self._initial = self.session.init_state(1)
        # (rows, state) of the last batched step, not yet written back to the pool.
        self._live: tuple[tuple[int, ...], Mapping[str, np.ndarray]] | None = None

    # -- streams ------------------------------------------------------------------------------
    @property
    def stream_ids(self) -> list[StreamId]:
        return list(self._streams)

    def add_stream(
        self, stream_id: StreamId, *, start_us: int | None = None, window_ms: float | None = None,
        sensor_hw: tuple[int, int] | None = None,
    ) -> None:
        """A new stream from the graph's initial state (window grid: `start_us` or its first event)."""
        if stream_id in self._streams:
            raise InputError(f"stream {stream_id!r} already exists")
        ms = float(window_ms if window_ms is not None else self.window_ms)
        window_us = window_us_from_ms(ms)
        hw = sensor_hw if sensor_hw is not None else self.sensor_hw
        if hw is None:
            raise InputError(f"{self.session.path}: metadata gives no sensor_hw for the frame input; pass sensor_hw")
        hw = (int(hw[0]), int(hw[1]))
        self._materialize()
        row = len(self._row_ids)
        capacity = len(next(iter(self._pool.values())))
        if row == capacity:  # full: double the capacity (rows are copied, so this stays rare)
            self._pool = {name: np.concatenate([pool, np.zeros((max(1, capacity), *pool.shape[1:]), pool.dtype)])
                          for name, pool in self._pool.items()}
        for name, pool in self._pool.items():
            pool[row] = self._initial[name][0]
        self._row_ids.append(stream_id)
        self._streams[stream_id] = _Stream(EventWindower(window_us, hw, start_us), ms, window_us, hw, start_us, row)

    def remove_stream(self, stream_id: StreamId) -> list[PoseEstimate]:
        """Drop a stream and its state row; returns the poses of windows it had already
        completed but not yet stepped (none, unless a call raised for another stream)."""
        poses = self._step_ready([stream_id]).get(stream_id, [])
        self._materialize()
        row = self._stream(stream_id).row
        last = len(self._row_ids) - 1
        if row != last:  # keep rows 0..n-1 dense: the last row moves into the hole
            moved = self._row_ids[last]
            for pool in self._pool.values():
                pool[row] = pool[last]
            self._row_ids[row] = moved
            self._streams[moved].row = row
        self._row_ids.pop()
        del self._streams[stream_id]
        return poses

    def stream_stats(self, stream_id: StreamId) -> StreamStats:
        """Counters of one stream; its step time is its share of the batched calls it was in,
        its overhead covers its own validation, windowing and LNES."""
        return self._stream(stream_id).stats

    def first_window_start_us(self, stream_id: StreamId) -> int | None:
        stream = self._stream(stream_id)
        return stream.start_us if stream.start_us is not None else stream.windower.first_event_us

    def state(self, stream_id: StreamId) -> dict[str, np.ndarray]:
        """A copy of one stream's recurrent state, batch of one."""
        self._materialize()
        row = self._stream(stream_id).row
        return {name: pool[row:row + 1].copy() for name, pool in self._pool.items()}

    # -- events in, poses out -----------------------------------------------------------------
    def push(self, stream_id: StreamId, x: np.ndarray, y: np.ndarray, t_us: np.ndarray, p: np.ndarray) -> list[PoseEstimate]:
        """Add a chunk to one stream; returns the poses of the windows it completed."""
        return self.push_many({stream_id: (x, y, t_us, p)}).get(stream_id, [])

    def push_many(self, chunks: Mapping[StreamId, EventChunk]) -> dict[StreamId, list[PoseEstimate]]:
        """Add one chunk to each named stream, then step every completed window, batched.

        A chunk that fails validation raises `InputError` naming its stream; that stream is
        unchanged, and the windows the call's other chunks completed are stepped (and
        returned) by the next call that concerns their streams.
        """
        began = time.perf_counter()
        for stream_id, (x, y, t, p) in chunks.items():
            stream = self._stream(stream_id)
            cut_began = time.perf_counter()
            try:
                windows = stream.windower.push(x, y, t, p)
            except InputError as exc:
                raise InputError(f"stream {stream_id!r}: {exc}") from exc
            stream.ready.extend(windows)
            stream.stats.events_received += int(np.asarray(t).shape[0])
            stream.stats.events_before_start = stream.windower.skipped_before_start
            stream.stats.overhead_seconds += time.perf_counter() - cut_began
        return self._step_ready(list(chunks), began)

    def flush(self, stream_id: StreamId, until_us: int) -> list[PoseEstimate]:
        """Emit the stream's windows ending at or before `until_us` (its earlier events are all in)."""
        return self.flush_many({stream_id: until_us}).get(stream_id, [])

    def flush_many(self, until_us: Mapping[StreamId, int]) -> dict[StreamId, list[PoseEstimate]]:
        began = time.perf_counter()
        for stream_id, until in until_us.items():
            self._stream(stream_id).ready.extend(self._stream(stream_id).windower.flush(until))
        return self._step_ready(list(until_us), began)

    def finish(self, stream_id: StreamId) -> list[PoseEstimate]:
        """End of one stream: its remaining complete windows (the stream stays registered)."""
        return self.finish_many([stream_id]).get(stream_id, [])

    def finish_many(self, stream_ids: Iterable[StreamId] | None = None) -> dict[StreamId, list[PoseEstimate]]:
        """End of the named streams (default: all), their last windows batched together."""
        began = time.perf_counter()
        ids = list(self._streams if stream_ids is None else stream_ids)
        for stream_id in ids:
            self._stream(stream_id).ready.extend(self._stream(stream_id).windower.finish())
        return self._step_ready(ids, began)

    # -- batched stepping ---------------------------------------------------------------------
    def _stream(self, stream_id: StreamId) -> _Stream:
        try:
            return self._streams[stream_id]
        except KeyError:
            raise InputError(f"unknown stream {stream_id!r}; add it with add_stream first") from None

    def _step_ready(self, stream_ids: list[StreamId], began: float | None = None) -> dict[StreamId, list[PoseEstimate]]:
        began = time.perf_counter() if began is None else began
        session_seconds = 0.0
        poses: dict[StreamId, list[PoseEstimate]] = {}
        streams = sorted({sid: self._stream(sid) for sid in stream_ids}.items(), key=lambda item: item[1].row)
        while True:
            due = [(sid, stream) for sid, stream in streams if stream.ready]
            if not due:
                break
            cap = self.max_batch or len(due)
            for lo in range(0, len(due), cap):
                session_seconds += self._step_rows(due[lo:lo + cap], poses)
        self.stats.step_seconds += session_seconds
        self.stats.overhead_seconds += time.perf_counter() - began - session_seconds
        return poses

    def _step_rows(self, due: list[tuple[StreamId, _Stream]], poses: dict[StreamId, list[PoseEstimate]]) -> float:
        """One batched session call over the next window of each stream in `due`."""
        frames = np.empty((len(due), 2, *self.frame_hw), np.float32)
        windows = np.empty(len(due), np.float32)
        cut = []
        for i, (_, stream) in enumerate(due):
            lnes_began = time.perf_counter()
            start_us, (x, y, t, p) = stream.ready.popleft()
            frames[i] = events_to_lnes(x, y, t, p, start_us, stream.window_us, *self.frame_hw, stream.sensor_hw)
            windows[i] = stream.window_ms
            cut.append((start_us, int(t.size)))
            stream.stats.overhead_seconds += time.perf_counter() - lnes_began
        rows = tuple(stream.row for _, stream in due)
        state = self._gather(rows)
        step_began = time.perf_counter()
        outputs, new_state = self.session.step(frames, state, windows)
        seconds = time.perf_counter() - step_began
        self._live = (rows, new_state)
        self.stats.session_calls += 1
        self.stats.rows_stepped += len(due)
        for i, (sid, stream) in enumerate(due):
            start_us, events = cut[i]
            stream.stats.windows += 1
            stream.stats.empty_windows += int(events == 0)
            stream.stats.events += events
            stream.stats.step_seconds += seconds / len(due)
            poses.setdefault(sid, []).append(PoseEstimate(
                t_us=start_us + stream.window_us, t_start_us=start_us, events=events,
                outputs={name: value[i] for name, value in outputs.items()},
            ))
        return seconds

    def _gather(self, rows: tuple[int, ...]) -> Mapping[str, Any]:
        """The states of `rows` as a batch, in that order."""
        if self._live is not None and self._live[0] == rows:
            return self._live[1]  # the last step ran the same rows: feed its state back as is
        self._materialize()
        if rows == tuple(range(len(rows))):  # leading rows: contiguous views, no copy
            return {name: pool[:len(rows)] for name, pool in self._pool.items()}
        index = np.asarray(rows)
        return {name: pool[index] for name, pool in self._pool.items()}

    def _materialize(self) -> None:
        """Write the last step's state back into the pool rows it belongs to."""
        if self._live is None:
            return
        rows, state = self._live
        self._live = None
        index = np.asarray(rows)
        for name, pool in self._pool.items():
            pool[index] = state[name]
