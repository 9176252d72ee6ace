"""One stream's windowing and stepping (e3dpsm/runtime/stream.py) without a graph: the
EventWindower against an explicit loop over the window grid, every refusal whole, and
StreamingPoseEstimator's counters and time split on a fake stepper and an injected clock.
tests/test_runtime.py runs the same code on a real graph."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from _timing_helpers import ManualClock, charge
from e3dpsm.errors import InputError
from e3dpsm.events import events_to_lnes
from e3dpsm.runtime import stream as stream_module
from e3dpsm.runtime.stream import EventWindower, StreamingPoseEstimator, StreamStats

SENSOR_HW = (12, 16)
FRAME_HW = (6, 8)
W = 20_000
T0 = 1_000_000


def _events(seed: int, n: int, lo: int, hi: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(lo, hi, n)).astype(np.int64)
    return (rng.integers(0, SENSOR_HW[1], n).astype(np.int32), rng.integers(0, SENSOR_HW[0], n).astype(np.int32),
            t, rng.integers(0, 2, n).astype(np.uint8))


def _chunks(events, sizes):
    out, at = [], 0
    for size in sizes:
        out.append(tuple(a[at:at + size] for a in events))
        at += size
    return out


def _grid(events, t0: int, end_us: int) -> list[tuple[int, int]]:
    """(start, event count) of every window [t0 + kW, t0 + (k+1)W) ending at or before end_us."""
    t = events[2]
    return [(t0 + k * W, int(((t >= t0 + k * W) & (t < t0 + (k + 1) * W)).sum()))
            for k in range((end_us - t0) // W)]


def _cut(windows) -> list[tuple[int, int]]:
    return [(start, int(chunk[2].size)) for start, chunk in windows]


@pytest.mark.parametrize("sizes", [[400], [1] * 50 + [350], [0, 7, 93, 0, 150, 150]])
def test_windows_are_the_grid_from_the_first_event(sizes) -> None:
    events = _events(1, 400, T0, T0 + 7 * W + 5_000)
    events[2][0] = T0
    windower = EventWindower(W, SENSOR_HW)
    got = []
    for chunk in _chunks(events, sizes):
        got += windower.push(*chunk)
        last = int(chunk[2][-1]) if chunk[2].size else None
        if last is not None:  # every window ending at or before the newest event is out, no more
            assert windower.next_start_us == T0 + ((last - T0) // W) * W
    got += windower.finish()
    last = int(events[2][-1])
    assert _cut(got) == _grid(events, T0, last + 1)
    assert windower.first_event_us == T0 and windower.last_t_us == last
    assert windower.pending_events == int((events[2] >= T0 + len(got) * W).sum())  # the dropped partial rest
    for (start, chunk), (want_start, _) in zip(got, _grid(events, T0, last + 1)):
        inside = (events[2] >= start) & (events[2] < start + W)
        assert start == want_start and np.array_equal(chunk[2], events[2][inside])
        assert np.array_equal(chunk[0], events[0][inside]) and np.array_equal(chunk[3], events[3][inside])


def test_finish_closes_a_window_ending_one_microsecond_after_the_last_event() -> None:
    events = _events(2, 50, T0, T0 + 2 * W)
    events[2][0], events[2][-1] = T0, T0 + 2 * W - 1
    windower = EventWindower(W, SENSOR_HW)
    assert _cut(windower.push(*events)) == _grid(events, T0, T0 + W)  # the event at 2W - 1 closes window 0 only
    assert _cut(windower.finish()) == [(T0 + W, int((events[2] >= T0 + W).sum()))]
    assert windower.finish() == [] and windower.pending_events == 0


def test_an_explicit_start_skips_and_counts_earlier_events() -> None:
    events = _events(3, 60, T0 - 5_000, T0 + 3 * W)
    windower = EventWindower(W, SENSOR_HW, start_us=T0)
    got = windower.push(*events) + windower.finish()
    early = int((events[2] < T0).sum())
    assert early > 0 and windower.skipped_before_start == early
    assert _cut(got) == _grid(events, T0, int(events[2][-1]) + 1)
    assert windower.first_event_us == int(events[2][0])  # the first event received, skipped or not


def test_flush_closes_time_no_event_reached_and_later_events_must_follow_it() -> None:
    windower = EventWindower(W, SENSOR_HW, start_us=T0)
    events = _events(4, 20, T0, T0 + W // 2)
    assert windower.push(*events) == []
    assert _cut(windower.flush(T0 + 3 * W + 7)) == [(T0, 20), (T0 + W, 0), (T0 + 2 * W, 0)]
    assert windower.flush(T0 + 3 * W + 8) == []
    late = _events(5, 3, T0 + 3 * W - 10, T0 + 3 * W - 1)
    with pytest.raises(InputError) as refused:
        windower.push(*late)
    assert str(refused.value) == (f"events out of order across chunks: a chunk starts at t = {int(late[2][0])} us, "
                                  f"before {T0 + 3 * W} us (the latest event, or the start of the window being "
                                  "filled); the stream must be sorted by time")
    assert windower.push(*_events(6, 3, T0 + 3 * W, T0 + 3 * W + 10)) == []  # at the floor: accepted


def test_a_chunk_older_than_the_last_event_is_refused_and_changes_nothing() -> None:
    windower = EventWindower(W, SENSOR_HW)
    first = _events(7, 10, T0, T0 + 100)
    windower.push(*first)
    before = (windower.last_t_us, windower.pending_events, windower.next_start_us)
    older = _events(8, 5, T0 + 50, T0 + 60)
    with pytest.raises(InputError) as refused:
        windower.push(*older)
    assert str(refused.value).startswith(f"events out of order across chunks: a chunk starts at t = {int(older[2][0])} "
                                         f"us, before {int(first[2][-1])} us")
    assert (windower.last_t_us, windower.pending_events, windower.next_start_us) == before
    empty = tuple(a[:0] for a in first)
    assert windower.push(*empty) == [] and windower.last_t_us == before[0]


@pytest.mark.parametrize("window_us", [0, -5])
def test_a_window_must_be_positive(window_us) -> None:
    with pytest.raises(InputError) as refused:
        EventWindower(window_us, SENSOR_HW)
    assert str(refused.value) == f"window length must be positive, got {window_us} us"
    assert EventWindower(1, SENSOR_HW).window_us == 1


def test_flush_before_any_event_is_refused_without_a_start() -> None:
    with pytest.raises(InputError) as refused:
        EventWindower(W, SENSOR_HW).flush(T0)
    assert str(refused.value) == "flush before any event: the window grid starts at the first event (or start_us)"
    assert EventWindower(W, SENSOR_HW).finish() == []
    assert _cut(EventWindower(W, SENSOR_HW, start_us=T0).flush(T0 + W)) == [(T0, 0)]


class FakeStepper:
    """feeds / run_feeds as a StepSession has them; state "h" += [1, frame sum, window ms]."""

    path = "fake.onnx"

    def __init__(self, clock=None, sensor_hw=SENSOR_HW) -> None:
        frame_input = {"name": "lnes"} if sensor_hw is None else {"name": "lnes", "sensor_hw": list(sensor_hw)}
        self.meta = SimpleNamespace(train_window_ms=20.0, frame_input=frame_input, frame_hw=FRAME_HW,
                                    joints=["head", "neck"])
        self.clock = clock

    def init_state(self, batch: int = 1) -> dict[str, np.ndarray]:
        return {"h": np.tile(np.array([0.0, 0.5, 0.25], np.float32), (batch, 1))}

    def feeds(self, frame, state, window):
        if self.clock:
            self.clock.advance(FEEDS_S)
        return {"frame": frame, "h": state["h"], "window": window}

    def run_feeds(self, feeds):
        if self.clock:
            self.clock.advance(RUN_S)
        added = np.stack([np.ones(1), feeds["frame"].reshape(1, -1).sum(1), feeds["window"]], 1)
        h = (feeds["h"] + added).astype(np.float32)
        return {"pose": h.copy()}, {"h": h}


# Seconds the injected clock charges: building feeds, the session's run, a window's LNES
# frame, each push / flush / finish of the windower.
FEEDS_S, RUN_S, LNES_S, CUT_S = 0.0002, 0.003, 0.001, 0.0005


@pytest.fixture()
def clock(monkeypatch):
    clock = ManualClock(50.0)
    monkeypatch.setattr(stream_module.time, "perf_counter", clock)
    charge(monkeypatch, stream_module, "events_to_lnes", clock, LNES_S)
    for name in ("push", "flush", "finish"):
        charge(monkeypatch, EventWindower, name, clock, CUT_S)
    return clock


def test_time_and_counters(clock) -> None:
    estimator = StreamingPoseEstimator(FakeStepper(clock), start_us=T0)
    events = _events(9, 120, T0 - 3_000, T0 + 4 * W)
    events[2][-1] = T0 + 4 * W - 1
    silent = (events[2] >= T0 + W) & (events[2] < T0 + 2 * W)
    events = tuple(a[~silent] for a in events)
    poses = []
    for chunk in _chunks(events, [30, len(events[2]) - 30]):
        poses += estimator.push(*chunk)
    poses += estimator.flush(T0 + 3 * W)  # nothing new to close
    poses += estimator.finish()
    stats = estimator.stats
    early = int((events[2] < T0).sum())
    assert (stats.windows, stats.empty_windows, stats.events_received, stats.events_before_start, stats.events) == (
        4, 1, len(events[2]), early, len(events[2]) - early)
    window = LNES_S + FEEDS_S + RUN_S
    assert stats.step_seconds == pytest.approx(4 * RUN_S)
    assert stats.overhead_seconds == pytest.approx(4 * CUT_S + 4 * (LNES_S + FEEDS_S))
    assert (stats.step_ms.count, stats.step_ms.min, stats.step_ms.max) == (4, pytest.approx(3.0), pytest.approx(3.0))
    assert (stats.window_ms.min, stats.window_ms.max) == (pytest.approx(window * 1e3), pytest.approx(window * 1e3))
    assert [p.events for p in poses] == [int(((events[2] >= T0 + k * W) & (events[2] < T0 + (k + 1) * W)).sum())
                                         for k in range(4)]
    figures = stats.to_dict()
    assert figures["mean_step_ms"] == pytest.approx(3.0) and figures["step_ms"]["count"] == 4
    assert figures["mean_overhead_ms"] == pytest.approx(stats.overhead_seconds * 1e3 / 4)


def test_poses_carry_the_state_and_the_window_times() -> None:
    estimator = StreamingPoseEstimator(FakeStepper(), window_ms=10, keep_frames=True)
    events = _events(10, 90, T0, T0 + 30_000)
    events[2][0], events[2][-1] = T0, T0 + 30_000 - 1
    poses = list(estimator.run(_chunks(events, [40, 50])))
    assert [(p.t_start_us, p.t_us) for p in poses] == [(T0 + k * 10_000, T0 + (k + 1) * 10_000) for k in range(3)]
    h = np.array([0.0, 0.5, 0.25])
    for k, pose in enumerate(poses):
        inside = (events[2] >= T0 + k * 10_000) & (events[2] < T0 + (k + 1) * 10_000)
        frame = events_to_lnes(*(a[inside] for a in events), T0 + k * 10_000, 10_000, *FRAME_HW, SENSOR_HW)
        h = h + [1.0, float(frame.sum(dtype=np.float32)), 10.0]
        np.testing.assert_allclose(pose.pose, h, rtol=1e-6)
        np.testing.assert_array_equal(pose.lnes, frame)
        assert pose.events == int(inside.sum())
    assert estimator.first_window_start_us == T0
    estimator.reset()  # a new stream: fresh state, grid and statistics
    fresh = estimator.stats
    assert (fresh.windows, fresh.events, fresh.events_received, fresh.step_seconds, fresh.step_ms.count) == (0, 0, 0, 0.0, 0)
    assert estimator.first_window_start_us is None
    np.testing.assert_array_equal(estimator.state["h"], [[0.0, 0.5, 0.25]])
    assert StreamingPoseEstimator(FakeStepper()).push(*_events(10, 5, T0, T0 + 10))[:1] == []
    assert all(p.lnes is None for p in StreamingPoseEstimator(FakeStepper()).run(_chunks(events, [90])))


def test_sensor_size_comes_from_the_caller_or_the_metadata() -> None:
    assert StreamingPoseEstimator(FakeStepper()).sensor_hw == SENSOR_HW
    assert StreamingPoseEstimator(FakeStepper(sensor_hw=None), sensor_hw=(30.0, 40.0)).sensor_hw == (30, 40)
    with pytest.raises(InputError) as refused:
        StreamingPoseEstimator(FakeStepper(sensor_hw=None))
    assert str(refused.value) == "fake.onnx: metadata gives no sensor_hw for the frame input; pass sensor_hw"
    estimator = StreamingPoseEstimator(FakeStepper(), start_us=123)
    assert (estimator.window_ms, estimator.window_us, estimator.first_window_start_us) == (20.0, 20_000, 123)
    assert estimator.joints == ["head", "neck"] and estimator.frame_hw == FRAME_HW


def test_stream_stats_figures() -> None:
    stats = StreamStats(windows=4, empty_windows=1, events=90, events_received=100, events_before_start=10,
                        step_seconds=0.012, overhead_seconds=0.004)
    assert stats.to_dict() == {"windows": 4, "empty_windows": 1, "events": 90, "events_received": 100,
                               "events_before_start": 10, "mean_step_ms": pytest.approx(3.0),
                               "mean_overhead_ms": pytest.approx(1.0), "step_seconds": 0.012, "overhead_seconds": 0.004}
    empty = StreamStats().to_dict()
    assert math.isnan(empty["mean_step_ms"]) and math.isnan(empty["mean_overhead_ms"])
    assert {k: v for k, v in empty.items() if not k.startswith("mean_")} == {
        "windows": 0, "empty_windows": 0, "events": 0, "events_received": 0, "events_before_start": 0,
        "step_seconds": 0.0, "overhead_seconds": 0.0}
    stats.step_ms.add(2.0)
    stats.window_ms.add(5.0)
    assert stats.to_dict()["step_ms"] == stats.step_ms.summary()
    assert stats.to_dict()["window_ms"] == stats.window_ms.summary()


def test_pending_events_are_counted_across_chunks() -> None:
    windower = EventWindower(W, SENSOR_HW)
    assert windower.pending_events == 0
    first, second = _events(11, 7, T0, T0 + 100), _events(12, 5, T0 + 100, T0 + 200)
    first[2][0] = T0  # the grid starts here
    assert windower.push(*first) == [] and windower.pending_events == 7
    assert windower.push(*second) == [] and windower.pending_events == 12
    windower.push(*_events(13, 3, T0 + W + 1, T0 + W + 9))  # closes window 0: its 12 events leave
    assert windower.pending_events == 3


def test_only_the_events_before_an_explicit_start_are_skipped() -> None:
    x, y, t, p = _events(14, 10, T0, T0 + 500)
    t[0] = T0 - 1  # the only event before the start
    windower = EventWindower(W, SENSOR_HW, start_us=T0)
    windower.push(x, y, t, p)
    assert windower.skipped_before_start == 1 and windower.pending_events == 9


def test_finish_before_any_event_with_a_start_closes_nothing() -> None:
    assert EventWindower(W, SENSOR_HW, start_us=T0).finish() == []


def test_finish_does_not_close_a_window_ending_two_microseconds_after_the_last_event() -> None:
    windower = EventWindower(W, SENSOR_HW, start_us=T0)
    events = _events(15, 30, T0, T0 + 2 * W - 2)
    events[2][-1] = T0 + 2 * W - 2
    got = windower.push(*events) + windower.finish()
    assert _cut(got) == [(T0, int((events[2] < T0 + W).sum()))]


def test_a_grid_starting_at_zero_closes_empty_windows_empty() -> None:
    assert _cut(EventWindower(W, SENSOR_HW, start_us=0).flush(2 * W)) == [(0, 0), (W, 0)]


def test_the_windower_checks_coordinates_against_its_sensor() -> None:
    windower = EventWindower(W, (12, 16))
    assert windower.sensor_hw == (12, 16)
    x, y, t, p = _events(16, 4, T0, T0 + 10)
    y[2] = 12  # one row below a 12-row sensor
    with pytest.raises(InputError):
        windower.push(x, y, t, p)
    y[2], x[1] = 11, 16  # a 16-column sensor has no column 16 either
    with pytest.raises(InputError):
        windower.push(x, y, t, p)


def test_a_pose_record_is_frozen_and_keeps_no_frame_unless_given() -> None:
    from e3dpsm.runtime.stream import PoseEstimate

    pose = PoseEstimate(t_us=T0 + W, t_start_us=T0, events=3, outputs={"pose": np.zeros((2, 3))})
    assert pose.lnes is None and pose.pose is pose.outputs["pose"]
    with pytest.raises(AttributeError):
        pose.t_us = 0
