"""MultiStreamEstimator's bookkeeping (e3dpsm/runtime/multistream.py) against a fake stepper
whose state counts what it was given: each row's state is [windows stepped, sum of its LNES
frames, sum of its window lengths] from an initial row that is not zero, so a stream whose
state row were mixed up with another's, reset or stepped twice shows at once. The real graphs
run the same code in tests/test_runtime_multistream.py."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from _timing_helpers import ManualClock, charge
from e3dpsm.errors import InputError
from e3dpsm.events import events_to_lnes
from e3dpsm.runtime.multistream import MultiStreamEstimator, MultiStreamStats

FRAME_HW = (6, 8)
META_SENSOR_HW = (12, 16)
INITIAL = np.array([0.0, 0.5, 0.25], np.float32)
WINDOW_US = 20_000


class CountingStepper:
    """A StreamStepper stand-in: state "h" [batch, 3] += [1, frame sum, window ms] per step."""

    path = "fake.onnx"

    def __init__(self, sensor_hw: tuple[int, int] | None = META_SENSOR_HW) -> None:
        frame_input = {"name": "lnes"} if sensor_hw is None else {"name": "lnes", "sensor_hw": list(sensor_hw)}
        self.meta = SimpleNamespace(train_window_ms=20.0, frame_input=frame_input, frame_hw=FRAME_HW,
                                    joints=["head", "neck"], states=[SimpleNamespace(name="h", shape=(3,))])
        self.calls: list[int] = []  # rows per call

    def init_state(self, batch: int = 1) -> dict[str, np.ndarray]:
        return {"h": np.tile(INITIAL, (batch, 1))}

    def step(self, frames, state, windows):
        assert frames.shape[1:] == (2, *FRAME_HW) and len(frames) == len(windows) == len(state["h"])
        self.calls.append(len(frames))
        added = np.stack([np.ones(len(frames)), frames.reshape(len(frames), -1).sum(1), windows], 1)
        new = {"h": (state["h"] + added).astype(np.float32)}
        return {"pose": new["h"].copy()}, new


def _events(seed: int, windows: int, t0: int = 1_000_000) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    n = 60 * windows
    t = np.sort(rng.integers(t0, t0 + windows * WINDOW_US, n)).astype(np.int64)
    t[0], t[-1] = t0, t0 + windows * WINDOW_US - 1  # the last window closes at finish
    return (rng.integers(0, META_SENSOR_HW[1], n).astype(np.uint16), rng.integers(0, META_SENSOR_HW[0], n).astype(np.uint16),
            t, rng.integers(0, 2, n).astype(np.int8))


def _between(events: tuple[np.ndarray, ...], lo: int, hi: int) -> tuple[np.ndarray, ...]:
    keep = (events[2] >= lo) & (events[2] < hi)
    return tuple(a[keep] for a in events)


def _expected_rows(events: tuple[np.ndarray, ...], windows: int, t0: int = 1_000_000) -> list[np.ndarray]:
    """The state after each window of one stream, by an explicit loop over its windows."""
    x, y, t, p = events
    h, rows = INITIAL.astype(np.float64).copy(), []
    for k in range(windows):
        start = t0 + k * WINDOW_US
        inside = (t >= start) & (t < start + WINDOW_US)
        frame = events_to_lnes(x[inside], y[inside], t[inside], p[inside], start, WINDOW_US, *FRAME_HW, META_SENSOR_HW)
        h = h + [1.0, float(frame.astype(np.float32).sum(dtype=np.float32)), 20.0]
        rows.append(h.copy())
    return rows


def test_stats_figures() -> None:
    stats = MultiStreamStats(session_calls=4, rows_stepped=10, step_seconds=0.02, overhead_seconds=0.005)
    assert stats.to_dict() == {"session_calls": 4, "rows_stepped": 10, "mean_batch": 2.5, "step_seconds": 0.02,
                               "overhead_seconds": 0.005, "mean_step_ms_per_pose": pytest.approx(2.0),
                               "mean_overhead_ms_per_pose": pytest.approx(0.5)}


def test_stats_before_any_step() -> None:
    figures = MultiStreamEstimator(CountingStepper()).stats.to_dict()
    assert {k: v for k, v in figures.items() if not (isinstance(v, float) and math.isnan(v))} == {
        "session_calls": 0, "rows_stepped": 0, "step_seconds": 0.0, "overhead_seconds": 0.0}
    assert all(math.isnan(figures[k]) for k in ("mean_batch", "mean_step_ms_per_pose", "mean_overhead_ms_per_pose"))


def test_sensor_size_from_the_metadata_or_the_caller() -> None:
    assert MultiStreamEstimator(CountingStepper()).sensor_hw == META_SENSOR_HW
    assert MultiStreamEstimator(CountingStepper(), sensor_hw=(100.0, 200.0)).sensor_hw == (100, 200)
    assert MultiStreamEstimator(CountingStepper(sensor_hw=None)).sensor_hw is None
    assert MultiStreamEstimator(CountingStepper(), window_ms=10).window_ms == 10.0
    assert MultiStreamEstimator(CountingStepper()).window_ms == 20.0


def test_a_stream_needs_a_sensor_size() -> None:
    estimator = MultiStreamEstimator(CountingStepper(sensor_hw=None))
    with pytest.raises(InputError) as refused:
        estimator.add_stream("cam")
    assert str(refused.value) == "fake.onnx: metadata gives no sensor_hw for the frame input; pass sensor_hw"
    estimator.add_stream("cam", sensor_hw=(12, 16))  # given by the stream: accepted
    assert estimator.stream_ids == ["cam"]


@pytest.mark.parametrize("max_batch", [0, -3])
def test_max_batch_must_be_positive(max_batch) -> None:
    with pytest.raises(InputError) as refused:
        MultiStreamEstimator(CountingStepper(), max_batch=max_batch)
    assert str(refused.value) == f"max_batch must be positive, got {max_batch}"


def test_stream_ids_are_checked() -> None:
    estimator = MultiStreamEstimator(CountingStepper())
    estimator.add_stream("cam")
    with pytest.raises(InputError) as twice:
        estimator.add_stream("cam")
    assert str(twice.value) == "stream 'cam' already exists"
    with pytest.raises(InputError) as unknown:
        estimator.push("other", *_events(0, 1))
    assert str(unknown.value) == "unknown stream 'other'; add it with add_stream first"


@pytest.mark.parametrize("max_batch, calls", [(None, [3, 3, 3]), (1, [1] * 9), (2, [2, 1, 2, 1, 2, 1])])
def test_rounds_are_cut_by_max_batch(max_batch, calls) -> None:
    stepper = CountingStepper()
    estimator = MultiStreamEstimator(stepper, max_batch=max_batch)
    streams = {f"cam{i}": _events(i, 4) for i in range(3)}
    for sid in streams:
        estimator.add_stream(sid, start_us=1_000_000)
    poses = estimator.push_many(streams)  # 3 complete windows each (the 4th waits for a later event)
    assert stepper.calls == calls
    assert estimator.stats.session_calls == len(calls) and estimator.stats.rows_stepped == 9
    for i, sid in enumerate(streams):
        want = _expected_rows(streams[sid], 3)
        assert [p.t_us for p in poses[sid]] == [1_000_000 + (k + 1) * WINDOW_US for k in range(3)]
        np.testing.assert_allclose([p.outputs["pose"] for p in poses[sid]], want, rtol=1e-6)


def test_rows_stay_with_their_streams_as_streams_come_and_go() -> None:
    """Five streams (the pool grows 0 -> 1 -> 2 -> 4 -> 8 rows), the first and a middle one leave
    (the last rows move into the holes), a new one joins; every stream's state is its own."""
    estimator = MultiStreamEstimator(CountingStepper())
    events = {f"s{i}": _events(10 + i, 6) for i in range(6)}
    cut = 1_000_000 + 3 * WINDOW_US
    for sid in list(events)[:5]:
        estimator.add_stream(sid, start_us=1_000_000)
    got: dict[str, list] = {sid: [] for sid in events}
    for sid, poses in estimator.push_many({sid: _between(events[sid], 0, cut) for sid in list(events)[:5]}).items():
        got[sid] += poses
    for sid in ("s0", "s2"):
        got[sid] += estimator.remove_stream(sid)
    estimator.add_stream("s5", start_us=1_000_000)
    np.testing.assert_allclose(estimator.state("s5")["h"], INITIAL[None])  # a new row starts from the initial state
    later = {sid: _between(events[sid], cut, 2**62) for sid in ("s1", "s3", "s4")}
    for sid, poses in estimator.push_many({**later, "s5": events["s5"]}).items():
        got[sid] += poses
    for sid, poses in estimator.finish_many().items():
        got[sid] += poses
    assert sorted(estimator.stream_ids) == ["s1", "s3", "s4", "s5"]
    for sid in ("s1", "s3", "s4", "s5"):
        want = _expected_rows(events[sid], 6)
        np.testing.assert_allclose([p.outputs["pose"] for p in got[sid]], want, rtol=1e-6)
        np.testing.assert_allclose(estimator.state(sid)["h"][0], want[-1], rtol=1e-6)
    for sid in ("s0", "s2"):  # stepped up to where they left
        np.testing.assert_allclose([p.outputs["pose"] for p in got[sid]], _expected_rows(events[sid], 6)[:2], rtol=1e-6)


def test_the_last_state_is_fed_back_only_to_the_same_rows() -> None:
    """Rows (0, 1) stepped together, then row 1 alone twice, then both: the last step's state is
    fed back only to the same rows; any other set reads the pool, written back first."""
    stepper = CountingStepper()
    estimator = MultiStreamEstimator(stepper)
    a, b = _events(1, 5), _events(2, 5)
    estimator.add_stream("a", start_us=1_000_000)
    estimator.add_stream("b", start_us=1_000_000)
    c1, c2 = 1_000_000 + 2 * WINDOW_US, 1_000_000 + 4 * WINDOW_US
    got = estimator.push_many({"a": _between(a, 0, c1), "b": _between(b, 0, c1)})  # window 0 of each
    got["b"] += estimator.push("b", *_between(b, c1, c2))  # b's windows 1, 2 alone
    for sid, poses in estimator.push_many({"a": _between(a, c1, 2**62), "b": _between(b, c2, 2**62)}).items():
        got[sid] += poses  # a: windows 1-3, b: window 3
    for sid, poses in estimator.finish_many().items():
        got[sid] += poses  # window 4 of each
    assert stepper.calls == [2, 1, 1, 2, 1, 1, 2]
    for sid, events in (("a", a), ("b", b)):
        assert [p.t_start_us for p in got[sid]] == [1_000_000 + k * WINDOW_US for k in range(5)]
        np.testing.assert_allclose([p.outputs["pose"] for p in got[sid]], _expected_rows(events, 5), rtol=1e-6)


# Seconds the injected clock charges: per session call and per row inside it, per window's
# LNES frame, per chunk cut into windows, per flush or finish of a stream's windower.
STEP_COST_S, ROW_COST_S, LNES_COST_S, PUSH_COST_S, CUT_COST_S = 0.001, 0.004, 0.002, 0.0005, 0.0003


@pytest.fixture()
def stepped(monkeypatch):
    from e3dpsm.runtime import multistream

    clock = ManualClock()
    monkeypatch.setattr(multistream.time, "perf_counter", clock)
    charge(monkeypatch, multistream, "events_to_lnes", clock, LNES_COST_S)
    charge(monkeypatch, multistream.EventWindower, "push", clock, PUSH_COST_S)
    charge(monkeypatch, multistream.EventWindower, "flush", clock, CUT_COST_S)
    charge(monkeypatch, multistream.EventWindower, "finish", clock, CUT_COST_S)

    class TimedStepper(CountingStepper):
        def step(self, frames, state, windows):
            clock.advance(STEP_COST_S + ROW_COST_S * len(frames))
            return super().step(frames, state, windows)

    return clock, TimedStepper()


def test_time_is_split_between_the_session_and_the_rest(stepped) -> None:
    stepper = stepped[1]
    estimator = MultiStreamEstimator(stepper)
    a, b = _events(1, 3), _events(2, 5)
    estimator.add_stream("a", start_us=1_000_000)
    estimator.add_stream("b", start_us=1_000_000)
    cut = 1_000_000 + 2 * WINDOW_US
    estimator.push_many({"a": _between(a, 0, cut), "b": _between(b, 0, cut)})  # round (a, b)
    estimator.push_many({"a": _between(a, cut, 2**62), "b": _between(b, cut, 2**62)})  # (a, b), (b), (b)
    estimator.flush_many({"a": 1_000_000, "b": 1_000_000})  # nothing left to close before then: no step
    estimator.finish_many()  # (a, b)
    assert stepper.calls == [2, 2, 1, 1, 2]
    step_total = 5 * STEP_COST_S + 8 * ROW_COST_S
    assert estimator.stats.step_seconds == pytest.approx(step_total)
    assert estimator.stats.overhead_seconds == pytest.approx(4 * PUSH_COST_S + 8 * LNES_COST_S + 4 * CUT_COST_S)
    shared, alone = (STEP_COST_S + 2 * ROW_COST_S) / 2, STEP_COST_S + ROW_COST_S
    stats_a, stats_b = estimator.stream_stats("a"), estimator.stream_stats("b")
    assert stats_a.step_seconds == pytest.approx(3 * shared)
    assert stats_b.step_seconds == pytest.approx(3 * shared + 2 * alone)
    assert stats_a.overhead_seconds == pytest.approx(2 * PUSH_COST_S + 3 * LNES_COST_S)
    assert stats_b.overhead_seconds == pytest.approx(2 * PUSH_COST_S + 5 * LNES_COST_S)
    figures = estimator.stats.to_dict()
    assert figures["mean_batch"] == 8 / 5 and figures["mean_step_ms_per_pose"] == pytest.approx(step_total * 1e3 / 8)


def test_stream_counters(stepped) -> None:
    estimator = MultiStreamEstimator(stepped[1])
    x, y, t, p = _events(3, 4)
    early = np.array([990_000, 995_000], np.int64)  # before the stream's start: skipped and counted
    silent = (t >= 1_000_000 + WINDOW_US) & (t < 1_000_000 + 2 * WINDOW_US)  # window 1 left empty
    keep = ~silent
    x, y, t, p = (np.concatenate([v[:2], v[keep]]) for v in (x, y, t, p))
    t[:2] = early
    estimator.add_stream("cam", start_us=1_000_000)
    estimator.push("cam", x[:50], y[:50], t[:50], p[:50])
    estimator.push("cam", x[50:], y[50:], t[50:], p[50:])
    estimator.finish("cam")
    stats = estimator.stream_stats("cam")
    assert (stats.windows, stats.empty_windows, stats.events_received, stats.events_before_start, stats.events) == (
        4, 1, len(t), 2, len(t) - 2)


def test_where_a_streams_windows_start() -> None:
    estimator = MultiStreamEstimator(CountingStepper())
    estimator.add_stream("given", start_us=900_000)
    estimator.add_stream("first_event")
    assert estimator.first_window_start_us("given") == 900_000
    assert estimator.first_window_start_us("first_event") is None  # no event yet
    estimator.push("first_event", *_events(4, 2, t0=1_234_567))
    estimator.push("given", *_events(4, 2, t0=1_000_000))
    assert estimator.first_window_start_us("first_event") == 1_234_567
    assert estimator.first_window_start_us("given") == 900_000


def test_a_bad_chunk_is_named_by_its_stream() -> None:
    from e3dpsm.runtime.stream import EventWindower

    x, y, t, p = _events(5, 2)
    t = t[::-1].copy()  # time runs backwards
    with pytest.raises(InputError) as inner:
        EventWindower(WINDOW_US, META_SENSOR_HW, 1_000_000).push(x, y, t, p)
    estimator = MultiStreamEstimator(CountingStepper())
    estimator.add_stream("cam", start_us=1_000_000)
    with pytest.raises(InputError) as refused:
        estimator.push("cam", x, y, t, p)
    assert str(refused.value) == f"stream 'cam': {inner.value}"


def test_a_steady_set_of_rows_gets_its_state_back_as_the_session_returned_it() -> None:
    """No gather or scatter while the same rows step: the state object the session returned
    is what it is given next (an IOBindingStepSession's device state stays on the device)."""
    fed_back = []

    class Recording(CountingStepper):
        last = None

        def step(self, frames, state, windows):
            fed_back.append(state is self.last)
            outputs, self.last = super().step(frames, state, windows)
            return outputs, self.last

    estimator = MultiStreamEstimator(Recording())
    estimator.add_stream("a", start_us=1_000_000)
    estimator.add_stream("b", start_us=1_000_000)
    estimator.push_many({"a": _events(1, 4), "b": _events(2, 4)})
    estimator.finish_many()
    assert fed_back == [False, True, True, True]
