"""Where events come from: a recording replayed at its own pace, or a live `dv://` source.

Both yield `Tick`s to the estimation loop: events to push, and for a recording the stream time
up to which every window is complete (the wall clock has reached it, so no earlier event is
still to come). A recording is released in `TICKS_PER_WINDOW` slices per window: the events of
each slice when the wall clock reaches the slice's end, scaled by --speed; a window's pose is
made at the tick of its end, whose scheduled wall time is the pose's `window_end_wall_ms`.
"""
from __future__ import annotations

import asyncio
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, AsyncIterator

import numpy as np

from e3dpsm.errors import ConfigError, DataError

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.data.sequence import EventStream
    from e3dpsm.runtime.stream import EventChunk

TICKS_PER_WINDOW = 4
# Live chunks waiting for the estimation loop: past this the reader thread blocks (bounded
# memory when the estimator falls behind; the source buffers or drops, as a camera does).
LIVE_QUEUE_CHUNKS = 256
LIVE_READER_THREAD = "e3dpsm-serve-live"


@dataclass(frozen=True)
class Tick:
    chunk: EventChunk | None  # events released now (None or empty: none)
    flush_until_us: int | None  # every window ending at or before it is complete (recordings)
    finish: bool  # end of the recording's pass: close the remaining complete windows
    wall_ms: float  # when these events arrived (scheduled replay time, or a live chunk's arrival)
    pass_index: int  # 0, then 1, 2, ... with --loop (a fresh state each pass)


class RecordingReplay:
    """A recording released at its own pace (x `speed`), optionally looped with a fresh state."""

    live = False

    def __init__(self, stream: EventStream, window_us: int, *, speed: float = 1.0, loop: bool = False) -> None:
        if len(stream) == 0:
            raise DataError("the recording holds no events; nothing to replay")
        if not (speed > 0 and math.isfinite(speed)):
            raise ConfigError(f"--speed must be a positive number, got {speed}")
        self.stream = stream
        self.sensor_hw = stream.sensor_hw
        self.window_us = int(window_us)
        self.speed = float(speed)
        self.loop = loop
        self.t0_us = int(stream.t_us[0])
        last = int(stream.t_us[-1])
        # One pass spans whole windows, so that later passes' t_us stay on one increasing grid.
        self.pass_span_us = (last - self.t0_us) // self.window_us * self.window_us + self.window_us
        self.tick_us = max(1, self.window_us // TICKS_PER_WINDOW)

    def pass_offset_us(self, pass_index: int) -> int:
        return pass_index * self.pass_span_us

    async def ticks(self) -> AsyncIterator[Tick]:
        s = self.stream
        last = int(s.t_us[-1])
        pass_index = 0
        while True:
            epoch_ms, start = time.time() * 1e3, time.perf_counter()
            lo = 0
            k = 1
            while True:
                until = self.t0_us + k * self.tick_us
                due = (until - self.t0_us) / 1e6 / self.speed
                delay = due - (time.perf_counter() - start)
                if delay > 0:
                    await asyncio.sleep(delay)
                end_reached = until > last
                hi = len(s) if end_reached else int(np.searchsorted(s.t_us, until, side="left"))
                chunk = (s.x[lo:hi], s.y[lo:hi], s.t_us[lo:hi], s.p[lo:hi]) if hi > lo else None
                lo = hi
                on_window_end = (until - self.t0_us) % self.window_us == 0
                yield Tick(chunk, until if on_window_end and not end_reached else None, end_reached,
                           epoch_ms + due * 1e3, pass_index)
                if end_reached:
                    break
                k += 1
            if not self.loop:
                return
            pass_index += 1

    def close(self) -> None:
        pass


class LiveFeed:
    """A live source's chunks, read on a thread (its iteration blocks) and handed to the loop."""

    live = True

    def __init__(self, source: Any) -> None:
        self.source = source
        self.sensor_hw = tuple(source.sensor_hw)
        self.stop_message: str | None = None  # why the source ended, for the status line
        self._stopping = threading.Event()

    def pass_offset_us(self, pass_index: int) -> int:
        return 0

    async def ticks(self) -> AsyncIterator[Tick]:
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue[Any] = asyncio.Queue()
        # Back-pressure, bounded memory: the reader thread takes a slot per chunk and waits when the
        # estimator falls behind; the loop frees the slot as it takes the chunk. The thread hands
        # chunks over with call_soon_threadsafe, so it never makes a coroutine a closed loop would drop.
        slots = threading.Semaphore(LIVE_QUEUE_CHUNKS)
        reader_gone = threading.Event()  # the loop stopped reading (generator closed): the thread ends
        done = object()

        def hand_over(item: Any) -> bool:
            try:
                loop.call_soon_threadsafe(queue.put_nowait, item)
                return True
            except RuntimeError:  # the loop has closed: nobody reads any more
                return False

        def put(item: Any) -> bool:
            while not (self._stopping.is_set() or reader_gone.is_set()):
                if slots.acquire(timeout=0.5):
                    return hand_over(item)
            return False

        def read() -> None:
            try:
                for chunk in self.source:
                    if self._stopping.is_set() or not put((chunk, time.time() * 1e3)):
                        break
                self.stop_message = "the live source stopped"
            except DataError as exc:
                self.stop_message = f"the live source stopped: {exc}"
            except Exception as exc:  # a reader bug must reach the page, not kill the thread silently
                self.stop_message = f"the live source failed: {type(exc).__name__}: {exc}"
            hand_over(done)

        thread = threading.Thread(target=read, name=LIVE_READER_THREAD, daemon=True)
        thread.start()
        try:
            while True:
                item = await queue.get()
                if item is done:
                    return
                slots.release()
                stream, arrived_ms = item
                yield Tick((stream.x, stream.y, stream.t_us, stream.p), None, False, arrived_ms, 0)
        finally:
            reader_gone.set()

    def close(self) -> None:
        if not self._stopping.is_set():
            self._stopping.set()
            self.source.close()
