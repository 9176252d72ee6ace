"""Where `serve`'s events come from (serve/source.py), on hand-made streams: a recording's
ticks written out here slice by slice (TICKS_PER_WINDOW slices a window, events released up
to each slice's end, windows flushed at their ends, the pass's end, loops on one time grid),
the refusals, and a live source read on its thread with each way it stops."""
from __future__ import annotations

import asyncio
import itertools

import numpy as np
import pytest

from e3dpsm.data.sequence import EventStream
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.serve.source import TICKS_PER_WINDOW, LiveFeed, RecordingReplay, Tick

SPEED = 1e6  # a pass of a few ms of events replays in microseconds


def _stream(t_us: list[int]) -> EventStream:
    n = len(t_us)
    return EventStream(x=np.arange(n, dtype=np.int32), y=np.arange(n, dtype=np.int32) + 100,
                       t_us=np.asarray(t_us, np.int64), p=(np.arange(n) % 2).astype(np.uint8), sensor_hw=(48, 64))


def _ticks(replay: RecordingReplay, limit: int | None = None) -> list[Tick]:
    async def collect() -> list[Tick]:
        ticks = replay.ticks()
        got = [tick async for tick in ticks] if limit is None else [await ticks.__anext__() for _ in range(limit)]
        await ticks.aclose()
        return got
    return asyncio.run(collect())


def _released(tick: Tick) -> list[int] | None:
    return None if tick.chunk is None else tick.chunk[2].tolist()


def test_a_recording_is_released_slice_by_slice_and_flushed_at_each_window_end() -> None:
    """Window 1000 us, slices of 250 us from t0 = 10,000: events at 10,000 (t0), 10,249 and
    10,250 (a slice's last microsecond and the next one's first), 11,600 and 12,100 (the last)."""
    replay = RecordingReplay(_stream([10_000, 10_249, 10_250, 11_600, 12_100]), 1000, speed=SPEED)
    assert TICKS_PER_WINDOW == 4 and replay.tick_us == 250 and replay.t0_us == 10_000 and replay.sensor_hw == (48, 64)
    assert replay.pass_span_us == 3000 and replay.pass_offset_us(0) == 0 and replay.pass_offset_us(2) == 6000
    got = _ticks(replay)
    # (released, flush_until_us, finish) for the slices ending at 10,250, 10,500, ..., 12,250
    assert [(_released(t), t.flush_until_us, t.finish, t.pass_index) for t in got] == [
        ([10_000, 10_249], None, False, 0),
        ([10_250], None, False, 0),
        (None, None, False, 0),
        (None, 11_000, False, 0),
        (None, None, False, 0),
        (None, None, False, 0),
        ([11_600], None, False, 0),
        (None, 12_000, False, 0),
        ([12_100], None, True, 0),  # the slice past the last event ends the pass: no flush, finish
    ]
    chunk = got[0].chunk
    assert chunk[0].tolist() == [0, 1] and chunk[1].tolist() == [100, 101] and chunk[3].tolist() == [0, 1]
    # each tick's wall time: the pass's start plus the slice's end in replay time
    np.testing.assert_allclose(np.diff([t.wall_ms for t in got]), 250 / 1e3 / SPEED, rtol=0, atol=1e-3)


def test_a_pass_whose_last_event_ends_a_window_still_finishes_after_it() -> None:
    replay = RecordingReplay(_stream([0, 1999]), 1000, speed=SPEED)
    got = _ticks(replay)
    assert replay.pass_span_us == 2000 and len(got) == 8
    assert [t.flush_until_us for t in got] == [None, None, None, 1000, None, None, None, None]
    assert got[-1].finish and _released(got[-1]) == [1999] and not any(t.finish for t in got[:-1])
    odd = RecordingReplay(_stream([0, 5]), 7, speed=SPEED)
    assert odd.tick_us == 1 and odd.pass_span_us == 7  # a window shorter than 4 slices: 1 us slices
    assert RecordingReplay(_stream([0, 5]), 3, speed=SPEED).tick_us == 1


def test_a_looped_recording_restarts_with_the_next_pass_index() -> None:
    replay = RecordingReplay(_stream([100, 900]), 1000, speed=SPEED, loop=True)
    got = _ticks(replay, limit=9)
    assert [t.pass_index for t in got] == [0, 0, 0, 0, 1, 1, 1, 1, 2]
    assert [_released(t) for t in got] == [[100], None, None, [900], [100], None, None, [900], [100]]
    assert [t.finish for t in got] == [False, False, False, True] * 2 + [False]
    assert RecordingReplay(_stream([100, 900]), 1000, speed=SPEED).loop is False


@pytest.mark.parametrize("speed", [0.0, -1.0, float("inf"), float("nan")])
def test_a_speed_that_is_not_a_positive_number_is_refused(speed) -> None:
    with pytest.raises(ConfigError) as refused:
        RecordingReplay(_stream([0, 1]), 1000, speed=speed)
    assert str(refused.value) == f"--speed must be a positive number, got {speed}"


def test_an_empty_recording_is_refused() -> None:
    with pytest.raises(DataError) as refused:
        RecordingReplay(_stream([]), 1000)
    assert str(refused.value) == "the recording holds no events; nothing to replay"
    replay = RecordingReplay(_stream([0]), 1000)
    assert replay.speed == 1.0 and replay.live is False and replay.close() is None


class FakeLive:
    """A live source: its chunks, then an end (none, a DataError or a bug); counts closes."""

    sensor_hw = [48, 64]

    def __init__(self, chunks: list[EventStream], error: Exception | None = None) -> None:
        self.chunks, self.error, self.closed = chunks, error, 0

    def __iter__(self):
        yield from self.chunks
        if self.error is not None:
            raise self.error

    def close(self) -> None:
        self.closed += 1


def _live_ticks(feed: LiveFeed) -> list[Tick]:
    async def collect() -> list[Tick]:
        return [tick async for tick in feed.ticks()]
    return asyncio.run(collect())


@pytest.mark.parametrize("error, message", [
    (None, "the live source stopped"),
    (DataError("publisher stopped"), "the live source stopped: publisher stopped"),
    (KeyError("x"), "the live source failed: KeyError: 'x'"),
])
def test_a_live_source_streams_its_chunks_and_says_why_it_stopped(error, message) -> None:
    chunks = [_stream([1, 2, 3]), _stream([4]), _stream([9, 10])]
    feed = LiveFeed(FakeLive(chunks, error))
    assert feed.live is True and feed.sensor_hw == (48, 64) and feed.pass_offset_us(3) == 0
    got = _live_ticks(feed)
    assert [_released(t) for t in got] == [[1, 2, 3], [4], [9, 10]]
    assert all(t.flush_until_us is None and not t.finish and t.pass_index == 0 for t in got)
    assert [t.wall_ms for t in got] == sorted(t.wall_ms for t in got) and got[0].wall_ms > 1.6e12  # arrival, epoch ms
    assert feed.stop_message == message


def test_closing_a_live_feed_closes_its_source_once_and_stops_the_reader() -> None:
    source = FakeLive([_stream([1])] * 5)
    feed = LiveFeed(source)
    feed.close()
    feed.close()
    assert source.closed == 1
    assert _live_ticks(feed) == []  # stopped before it read: no chunk is handed on
    chunks = itertools.count()

    class Endless(FakeLive):
        def __iter__(self):
            for k in chunks:
                yield _stream([k])

    feed = LiveFeed(Endless([]))

    async def first_then_close() -> list[Tick]:
        ticks = feed.ticks()
        got = [await ticks.__anext__() for _ in range(3)]
        feed.close()  # the reader, blocked on a full queue or reading, stops within its 0.5 s poll
        await ticks.aclose()
        return got

    got = asyncio.run(first_then_close())
    assert [_released(t) for t in got] == [[0], [1], [2]] and feed.source.closed == 1
