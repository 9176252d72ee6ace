"""Where `serve`'s events come from (serve/source.py), on hand-made streams: a recording's
ticks written out here slice by slice (TICKS_PER_WINDOW slices a window, events released up
to each slice's end, windows flushed at their ends, the pass's end, loops on one time grid),
the refusals, and a live source read on its thread with each way it stops."""
from __future__ import annotations

import asyncio
import itertools
import time

import numpy as np
import pytest

from e3dpsm.data.sequence import EventStream
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.serve.source import LIVE_QUEUE_CHUNKS, TICKS_PER_WINDOW, LiveFeed, RecordingReplay, Tick

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


# -- on an injected clock -------------------------------------------------------------------------
class FakeClock:
    """source.py's `time` (wall and monotonic clocks) and its sleep: the monotonic clock moves
    only when slept on, or by `overrun` seconds after the k-th sleep (a slow estimator)."""

    EPOCH_S = 1_700_000_000.0

    def __init__(self, overrun: dict[int, float] | None = None, start: float = 0.0) -> None:
        self.now, self.sleeps, self.overrun = start, [], overrun or {}

    def time(self) -> float:
        return self.EPOCH_S

    def perf_counter(self) -> float:
        return self.now

    async def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds + self.overrun.get(len(self.sleeps), 0.0)


def _install(monkeypatch, fake: FakeClock) -> FakeClock:
    import types

    import e3dpsm.serve.source as source

    monkeypatch.setattr(source, "time", fake)
    monkeypatch.setattr(source, "asyncio", types.SimpleNamespace(sleep=fake.sleep))
    return fake


@pytest.fixture()
def clock(monkeypatch):
    return _install(monkeypatch, FakeClock(start=100.0))  # a monotonic clock far from 0


def test_each_slice_waits_for_its_time_and_is_stamped_with_it(clock) -> None:
    """Speed 2 from t0 = 10,100 (not on the window grid): slices of 250 us of stream time are
    125 us of wall time; each tick's wall time is the pass's start plus its slice's end."""
    replay = RecordingReplay(_stream([10_100, 10_400, 12_000]), 1000, speed=2.0)
    got = _ticks(replay)
    ends = [250 * k / 1e6 / 2.0 for k in range(1, 9)]  # seconds after the pass's start; 12,100 ends it
    assert clock.sleeps == pytest.approx(np.diff([0.0, *ends]).tolist(), abs=1e-12)
    assert [t.wall_ms for t in got] == pytest.approx([FakeClock.EPOCH_S * 1e3 + e * 1e3 for e in ends], abs=1e-6)
    assert [t.flush_until_us for t in got] == [None, None, None, 11_100, None, None, None, None]
    assert [_released(t) for t in got] == [[10_100], [10_400], None, None, None, None, None, [12_000]]
    assert got[-1].finish and replay.pass_span_us == 2000


def test_a_slice_whose_time_has_come_is_not_waited_for(monkeypatch) -> None:
    """After the 2nd sleep the estimator overran by 1.5 slices: the 3rd slice is released at
    once (no sleep), the 4th waits half a slice. A slice due exactly now is not slept for
    either (the clock set to the 3rd slice's due time, as the replay computes it)."""
    fake = _install(monkeypatch, FakeClock(overrun={2: 1.5 * 250 / 1e6}, start=100.0))
    _ticks(RecordingReplay(_stream([0, 999]), 1000, speed=1.0))
    assert fake.sleeps == pytest.approx([250e-6, 250e-6, 125e-6], abs=1e-9)

    class ExactlyDue(FakeClock):
        async def sleep(self, seconds: float) -> None:
            self.sleeps.append(seconds)
            self.now = 750 / 1e6 / 1.0 if len(self.sleeps) == 2 else self.now + seconds

    fake = _install(monkeypatch, ExactlyDue())
    _ticks(RecordingReplay(_stream([0, 999]), 1000, speed=1.0))
    assert len(fake.sleeps) == 3 and fake.sleeps[2] == pytest.approx(250e-6, abs=1e-12)


def test_a_last_event_on_a_slice_end_is_released_by_the_next_slice() -> None:
    got = _ticks(RecordingReplay(_stream([0, 500]), 1000, speed=SPEED))
    assert [(_released(t), t.finish) for t in got] == [([0], False), (None, False), ([500], True)]


def test_ticks_are_immutable() -> None:
    import dataclasses

    tick = Tick(None, None, False, 0.0, 0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        tick.finish = True


def test_a_live_chunk_is_stamped_with_its_arrival_and_the_reader_is_a_named_daemon(monkeypatch) -> None:
    import threading

    import e3dpsm.serve.source as source

    monkeypatch.setattr(source.time, "time", lambda: FakeClock.EPOCH_S)
    seen: list[tuple[str, bool]] = []

    class Watching(FakeLive):
        def __iter__(self):
            seen.append((threading.current_thread().name, threading.current_thread().daemon))
            yield from self.chunks

    feed = LiveFeed(Watching([_stream([1]), _stream([2])]))
    assert feed.stop_message is None  # nothing said before it stops
    got = _live_ticks(feed)
    assert [t.wall_ms for t in got] == [FakeClock.EPOCH_S * 1e3] * 2
    assert seen == [("e3dpsm-serve-live", True)]  # a blocked reader never keeps the process alive


def _wait_until_steady(read, seconds: float = 0.4) -> int:
    """`read()` once it has not changed for `seconds` (a thread that stopped or blocked)."""
    value, since = read(), time.monotonic()
    while time.monotonic() - since < seconds:
        time.sleep(0.02)
        if read() != value:
            value, since = read(), time.monotonic()
    return value


def test_a_live_reader_blocks_when_the_loop_falls_behind_and_loses_nothing() -> None:
    """The loop takes one chunk, then stops reading for over a second (past the reader's 0.5 s
    polls): the reader stops at the queue's bound, and every chunk then arrives in order."""
    total = LIVE_QUEUE_CHUNKS + 40
    read_so_far: list[int] = []

    class Counting(FakeLive):
        def __iter__(self):
            for k in range(total):
                read_so_far.append(k)
                yield _stream([k])

    feed = LiveFeed(Counting([]))

    def blocked() -> int:
        """The chunks read once the reader has filled the queue (waited for, however slow a
        loaded host makes it), then still after more than two of its 0.5 s polls."""
        deadline = time.monotonic() + 30.0
        while len(read_so_far) < 1 + LIVE_QUEUE_CHUNKS + 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(1.2)
        return len(read_so_far)

    async def slow_loop() -> tuple[list[int], int]:
        ticks = feed.ticks()
        got = [_released(await ticks.__anext__())[0]]
        blocked_at = await asyncio.get_running_loop().run_in_executor(None, blocked)
        got += [_released(tick)[0] async for tick in ticks]
        return got, blocked_at

    got, blocked_at = asyncio.run(slow_loop())
    assert got == list(range(total))
    assert LIVE_QUEUE_CHUNKS == 256  # docs/serve.md
    # one taken, LIVE_QUEUE_CHUNKS queued, one waiting to be put: the reader read no further
    assert blocked_at == 1 + LIVE_QUEUE_CHUNKS + 1


def test_a_closed_live_feed_stops_reading_its_source() -> None:
    read_so_far: list[int] = []

    class Endless(FakeLive):
        def __iter__(self):
            for k in itertools.count():
                read_so_far.append(k)
                yield _stream([k])

    feed = LiveFeed(Endless([]))

    async def take_two_then_close() -> None:
        ticks = feed.ticks()
        for _ in range(2):
            await ticks.__anext__()
        feed.close()
        await ticks.aclose()

    asyncio.run(take_two_then_close())
    stopped_at = _wait_until_steady(lambda: len(read_so_far))
    assert stopped_at <= 2 + LIVE_QUEUE_CHUNKS + 2  # it stopped, within a queue's worth


def test_a_live_reader_ends_quietly_when_the_loop_stops_reading() -> None:
    """The loop takes two chunks and drops the iterator without closing the feed, while the
    source has more chunks than the queue holds: the reader thread ends on its own while the
    loop still runs (it no longer waits for a slot nobody frees), and once the loop has ended
    it raised nothing and left no coroutine unawaited (it hands chunks over without making any)."""
    import gc
    import threading
    import warnings

    from e3dpsm.serve.source import LIVE_READER_THREAD

    read_so_far: list[int] = []

    class Plenty(FakeLive):
        def __iter__(self):
            for k in range(LIVE_QUEUE_CHUNKS * 4):
                read_so_far.append(k)
                yield _stream([k])

    class Slow(FakeLive):
        def __iter__(self):
            for k in range(LIVE_QUEUE_CHUNKS * 4):
                time.sleep(0.2 if k >= 2 else 0)
                yield _stream([k])

    before = set(threading.enumerate())  # readers of other tests in this process are not ours to wait for

    def reader_alive() -> bool:
        return any(t.name == LIVE_READER_THREAD and t not in before for t in threading.enumerate())

    def wait_for_the_reader_to_end() -> bool:
        deadline = time.monotonic() + 10.0
        while reader_alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        return not reader_alive()

    raised: list[BaseException] = []
    old_hook, threading.excepthook = threading.excepthook, lambda args: raised.append(args.exc_value)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")

            async def take_two_then_leave() -> bool:
                ticks = LiveFeed(Plenty([])).ticks()
                for _ in range(2):
                    await ticks.__anext__()
                await ticks.aclose()
                return await asyncio.get_running_loop().run_in_executor(None, wait_for_the_reader_to_end)

            assert asyncio.run(take_two_then_leave()) is True
            assert len(read_so_far) <= 2 + LIVE_QUEUE_CHUNKS + 2  # it stopped reading, not read to the end

            async def take_two_then_close_the_feed() -> bool:  # the iterator stays open
                feed = LiveFeed(Plenty([]))
                ticks = feed.ticks()
                for _ in range(2):
                    await ticks.__anext__()
                feed.close()
                ended = await asyncio.get_running_loop().run_in_executor(None, wait_for_the_reader_to_end)
                await ticks.aclose()
                return ended

            assert asyncio.run(take_two_then_close_the_feed()) is True

            loop = asyncio.new_event_loop()  # a loop closed under the iterator, which is never finalised
            kept = LiveFeed(Plenty([])).ticks()
            for _ in range(2):
                loop.run_until_complete(kept.__anext__())
            loop.close()
            assert wait_for_the_reader_to_end()

            async def take_two_then_end() -> None:  # the loop ends while the reader is mid-chunk
                ticks = LiveFeed(Slow([])).ticks()
                for _ in range(2):
                    await ticks.__anext__()
                await ticks.aclose()

            asyncio.run(take_two_then_end())
            assert wait_for_the_reader_to_end()
            gc.collect()
        assert raised == []
        assert [str(w.message) for w in caught if "never awaited" in str(w.message)] == []
    finally:
        threading.excepthook = old_hook
