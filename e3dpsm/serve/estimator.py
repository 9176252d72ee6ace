"""The estimation loop: source ticks in, poses broadcast to every client.

onnxruntime runs on worker threads (one per graph, so `--compare` steps both graphs at once),
never on the event loop, so sockets stay responsive while a step runs. The loop awaits each
tick's work before the next tick, so windows are stepped in order and states carried; a slow
step makes later ticks late (their latency shows it) but never skips or reorders a window.
"""
from __future__ import annotations

import asyncio
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from e3dpsm.serve import protocol
from e3dpsm.serve.source import Tick
from e3dpsm.utils.stats import LogHistogram

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.runtime import PoseEstimate, StepSession
    from e3dpsm.runtime.render_stream import GroundTruthTrack
    from e3dpsm.serve.clients import ClientHub

RECENT_STEPS = 50  # the stats message's median step is over the latest ones
SERVER_HZ_SPAN_MS = 1e3  # the stats message's server_hz counts the poses sent within the latest second


@dataclass
class EngineStats:
    """Counters and fixed-size histograms: the same memory after a minute or a week."""

    poses: int = 0
    passes: int = 0
    events: int = 0
    step_ms: LogHistogram = field(default_factory=LogHistogram)
    compare_step_ms: LogHistogram = field(default_factory=LogHistogram)
    ready_latency_ms: LogHistogram = field(default_factory=LogHistogram)  # window end -> pose message built
    recent_step_ms: deque[float] = field(default_factory=lambda: deque(maxlen=RECENT_STEPS))
    late_ticks: int = 0  # ticks handled more than one window after their scheduled time
    stop_reason: str | None = None


class _Graph:
    """One graph's streaming estimator and its own worker thread."""

    def __init__(self, session: StepSession, window_ms: float, sensor_hw: tuple[int, int], keep_frames: bool) -> None:
        from e3dpsm.runtime import StreamingPoseEstimator

        self.estimator = StreamingPoseEstimator(session, window_ms=window_ms, sensor_hw=sensor_hw,
                                                keep_frames=keep_frames)
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="e3dpsm-serve-step")

    def work(self, tick: Tick) -> tuple[list[PoseEstimate], float]:
        """The tick's poses and the seconds spent inside onnxruntime for them."""
        est = self.estimator
        before = est.stats.step_seconds
        poses = est.push(*tick.chunk) if tick.chunk is not None else []
        if tick.flush_until_us is not None:
            poses += est.flush(tick.flush_until_us)
        if tick.finish:
            poses += est.finish()
        return poses, est.stats.step_seconds - before

    async def run(self, tick: Tick) -> tuple[list[PoseEstimate], float]:
        return await asyncio.get_running_loop().run_in_executor(self.worker, self.work, tick)

    def close(self) -> None:
        self.worker.shutdown(wait=False, cancel_futures=True)


class ServeEngine:
    graph_type = _Graph  # one per graph and pass (tests substitute scripted graphs)

    def __init__(self, source: Any, hub: ClientHub, session: StepSession, *, window_ms: float,
                 compare: StepSession | None = None, ground_truth: GroundTruthTrack | None = None,
                 frame_hz: float = 10.0, frame_max_width: int = 128, stats_period_s: float = 1.0,
                 wall_clock: Callable[[], float] = time.time,
                 interval_clock: Callable[[], float] = time.perf_counter) -> None:
        """`wall_clock`: seconds since the epoch, the time base of ticks' `wall_ms` and of the
        messages' wall times; `interval_clock`: monotonic seconds, for the stats period. Tests
        inject both."""
        self.source, self.hub = source, hub
        self.wall_clock, self.interval_clock = wall_clock, interval_clock
        self.window_ms = window_ms
        self.session, self.compare_session = session, compare
        self.ground_truth = ground_truth
        self.frame_period_ms = 1e3 / frame_hz
        self.frame_max_width = frame_max_width
        self.stats_period_s = stats_period_s
        self.stats = EngineStats()
        self._recent_wall: deque[float] = deque()  # send times within the last second (server_hz), oldest first
        self._last_frame_ms = -float("inf")
        self._last_stats = -float("inf")
        self._seq = 0
        self._graphs: list[_Graph] = []
        self._new_pass(0)
        self.window_us = self._graphs[0].estimator.window_us

    def _new_pass(self, pass_index: int) -> None:
        for graph in self._graphs:
            graph.close()
        sensor_hw = tuple(self.source.sensor_hw)
        self._graphs = [self.graph_type(self.session, self.window_ms, sensor_hw, keep_frames=True)]
        if self.compare_session is not None:
            self._graphs.append(self.graph_type(self.compare_session, self.window_ms, sensor_hw, keep_frames=False))
        self._pass = pass_index
        self.stats.passes = pass_index + 1

    async def run(self) -> str:
        """Replay until the source ends (the caller cancels it for Ctrl-C or --duration-s);
        returns why it ended."""
        ticks = self.source.ticks()
        try:
            async for tick in ticks:
                if tick.pass_index != self._pass:
                    self._new_pass(tick.pass_index)
                    self.hub.set_status(protocol.status("loop", f"recording restarted (pass {tick.pass_index + 1}), fresh state"))
                await self._handle(tick)
            if self.source.live:  # the live source ended: close what its last events completed
                await self._handle(Tick(None, None, True, self._wall_ms(), self._pass))
                return "source stopped"
            return "recording ended"
        finally:
            await ticks.aclose()
            for graph in self._graphs:
                graph.close()

    async def _handle(self, tick: Tick) -> None:
        results = await asyncio.gather(*(graph.run(tick) for graph in self._graphs))
        poses, step_s = results[0]
        compare = results[1] if len(results) > 1 else None
        if tick.chunk is not None:
            self.stats.events += int(tick.chunk[2].shape[0])
        if not poses:
            self._maybe_stats()
            return
        lateness_ms = self._wall_ms() - tick.wall_ms
        if lateness_ms > self.window_ms:
            self.stats.late_ticks += 1
        per_pose_ms = step_s * 1e3 / len(poses)
        cmp_ms = None if compare is None else compare[1] * 1e3 / max(len(compare[0]), 1)
        offset = self.source.pass_offset_us(self._pass)
        for i, estimate in enumerate(poses):
            cmp_pose = compare[0][i].pose if compare is not None and i < len(compare[0]) else None
            gt = None if self.ground_truth is None else self.ground_truth.at(estimate.t_us, self.window_us)
            # A window closed by this tick ended at its scheduled time, or earlier when a tick
            # closes several (a live chunk, a late loop): the tick's time is the arrival time.
            now_ms = self._wall_ms()
            message = protocol.pose(
                seq=self._seq, t_us=estimate.t_us + offset, pose_mm=estimate.pose, compare_mm=cmp_pose, gt_mm=gt,
                window_end_wall_ms=tick.wall_ms, sent_wall_ms=now_ms, step_ms=per_pose_ms,
                compare_step_ms=cmp_ms, events=estimate.events,
            )
            self.hub.broadcast_pose(message)
            self._seq += 1
            self.stats.poses += 1
            self._recent_wall.append(now_ms)
            self._forget_before(now_ms - SERVER_HZ_SPAN_MS)
            self.stats.step_ms.add(per_pose_ms)
            self.stats.recent_step_ms.append(per_pose_ms)
            self.stats.ready_latency_ms.add(now_ms - tick.wall_ms)
            if cmp_ms is not None:
                self.stats.compare_step_ms.add(cmp_ms)
        await self._maybe_frame(poses[-1], offset)
        self._maybe_stats()

    def _forget_before(self, oldest_ms: float) -> None:
        """Drop the send times before `oldest_ms`: the deque holds one second of poses at any rate."""
        while self._recent_wall and self._recent_wall[0] < oldest_ms:
            self._recent_wall.popleft()

    def _wall_ms(self) -> float:
        return self.wall_clock() * 1e3

    async def _maybe_frame(self, estimate: PoseEstimate, offset: int) -> None:
        now_ms = self._wall_ms()
        if estimate.lnes is None or now_ms - self._last_frame_ms < self.frame_period_ms or not self.hub.count_open():
            return
        self._last_frame_ms = now_ms
        # After the pose went out, so that building the image never delays a pose.
        text = await asyncio.get_running_loop().run_in_executor(
            self._graphs[0].worker, lambda: protocol.frame(seq=self._seq - 1, t_us=estimate.t_us + offset,
                                                           lnes=estimate.lnes, max_width=self.frame_max_width))
        self.hub.broadcast_frame(text)

    def _maybe_stats(self) -> None:
        now = self.interval_clock()
        if now - self._last_stats < self.stats_period_s:
            return
        self._last_stats = now
        wall = self._wall_ms()
        self._forget_before(wall - SERVER_HZ_SPAN_MS)
        recent_steps = list(self.stats.recent_step_ms)
        self.hub.broadcast_stats(poses=self.stats.poses, server_hz=len(self._recent_wall),
                                 step_ms=float(np.median(recent_steps)) if recent_steps else None,
                                 clients=self.hub.count_open(), passes=self.stats.passes)
