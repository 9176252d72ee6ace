"""The viewer's estimation loop (serve/estimator.py) on injected clocks: scripted graphs and a
scripted source, so every field of every message it sends is written out here; and its real
per-graph worker on the numpy-sized toy step graph (tests/_toy_step_graph.py)."""
from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest

from _timing_helpers import ManualClock
from _toy_step_graph import INIT, toy_numpy_step, toy_step_graph
from e3dpsm.runtime.stream import PoseEstimate
from e3dpsm.serve import protocol
from e3dpsm.serve.estimator import RECENT_STEPS, ServeEngine, _Graph
from e3dpsm.serve.source import Tick

WINDOW_MS = 20.0
WINDOW_US = 20_000


def estimate(t_us: int, value: float, events: int = 7, lnes: np.ndarray | None = None) -> PoseEstimate:
    return PoseEstimate(t_us=t_us, t_start_us=t_us - WINDOW_US, events=events,
                        outputs={"pose": np.full((2, 3), value, np.float32)}, lnes=lnes)


class ScriptedEstimator:
    window_us = WINDOW_US


class ScriptedGraph:
    """What ServeEngine needs of a graph: `run(tick)` -> (poses, seconds in the runtime), from a
    script shared by all graphs of one role (main, compare), so a new pass reads on."""

    scripts: dict[bool, list[tuple[list[PoseEstimate], float]]] = {}
    made: list["ScriptedGraph"] = []

    def __init__(self, session: Any, window_ms: float, sensor_hw: tuple[int, int], keep_frames: bool) -> None:
        self.session, self.window_ms, self.sensor_hw, self.keep_frames = session, window_ms, sensor_hw, keep_frames
        self.estimator, self.ticks, self.closed = ScriptedEstimator(), [], 0
        self.worker = None  # frames are built on the loop's default executor
        ScriptedGraph.made.append(self)

    async def run(self, tick: Tick) -> tuple[list[PoseEstimate], float]:
        self.ticks.append(tick)
        return self.scripts[self.keep_frames].pop(0)

    def close(self) -> None:
        self.closed += 1


class ScriptedEngine(ServeEngine):
    graph_type = ScriptedGraph


class Hub:
    """Records what the engine broadcasts, in order."""

    def __init__(self, clients: int = 1) -> None:
        self.clients, self.sent = clients, []

    def broadcast_pose(self, message: protocol.PoseMessage) -> None:
        self.sent.append(("pose", json.loads(message.text)))

    def broadcast_frame(self, text: str) -> None:
        self.sent.append(("frame", json.loads(text)))

    def broadcast_stats(self, **fields: Any) -> None:
        self.sent.append(("stats", fields))

    def set_status(self, text: str) -> None:
        self.sent.append(("status", json.loads(text)))

    def count_open(self) -> int:
        return self.clients

    def of(self, kind: str) -> list[dict[str, Any]]:
        return [message for k, message in self.sent if k == kind]


class Source:
    """Scripted ticks; before each, the wall clock moves to the tick's `at` seconds."""

    sensor_hw = (4, 6)

    def __init__(self, clock: ManualClock, ticks: list[tuple[float, Tick]], live: bool = False) -> None:
        self.clock, self.script, self.live, self.closed = clock, ticks, live, 0

    def pass_offset_us(self, pass_index: int) -> int:
        return 1_000_000 * pass_index

    async def ticks(self):
        try:
            for at, tick in self.script:
                self.clock.now = at
                yield tick
        finally:
            self.closed += 1


def tick(wall_ms: float, events: int = 0, pass_index: int = 0, finish: bool = False) -> Tick:
    chunk = None if not events else (np.zeros(events, np.int16), np.zeros(events, np.int16),
                                     np.arange(events, dtype=np.int64), np.ones(events, np.int8))
    return Tick(chunk, None, finish, wall_ms, pass_index)


@pytest.fixture(autouse=True)
def _fresh_script():
    ScriptedGraph.scripts, ScriptedGraph.made = {True: [], False: []}, []
    yield


def engine_for(source: Source, hub: Hub, clock: ManualClock, *, compare: bool = False, ground_truth: Any = None,
               frame_hz: float = 10.0, stats_period_s: float = 1.0, interval: ManualClock | None = None) -> ServeEngine:
    return ScriptedEngine(source, hub, "main-session", window_ms=WINDOW_MS, compare="cmp-session" if compare else None,
                          ground_truth=ground_truth, frame_hz=frame_hz, frame_max_width=4,
                          stats_period_s=stats_period_s, wall_clock=clock, interval_clock=interval or clock)


def test_every_pose_message_field_comes_from_its_tick_graphs_and_clock() -> None:
    """Two ticks: the first closes three windows (runtime calls of 9 ms for the three: 3 ms
    each), the second none; the compare graph returns two poses for them in 8 ms (4 ms each;
    the third pose gets None)."""
    clock = ManualClock()
    ScriptedGraph.scripts[True] = [([estimate(40_000, 1.0, events=5), estimate(60_000, 2.0, events=0),
                                     estimate(80_000, 3.0, events=2)], 0.009), ([], 0.0)]
    ScriptedGraph.scripts[False] = [([estimate(40_000, -1.0), estimate(60_000, -2.0)], 0.008), ([], 0.0)]

    class Truth:
        def at(self, t_us: int, window_us: int) -> np.ndarray | None:
            assert window_us == WINDOW_US
            return np.full((2, 3), 9.0) if t_us == 60_000 else None

    hub = Hub(clients=0)
    source = Source(clock, [(100.010, tick(100_000.0, events=11)), (100.030, tick(100_020.0, events=3))])
    engine = engine_for(source, hub, clock, compare=True, ground_truth=Truth())
    assert asyncio.run(engine.run()) == "recording ended"

    poses = hub.of("pose")
    assert [p["seq"] for p in poses] == [0, 1, 2] and [p["t_us"] for p in poses] == [40_000, 60_000, 80_000]
    assert [p["pose"] for p in poses] == [[[v] * 3] * 2 for v in (1.0, 2.0, 3.0)]
    assert [p["compare"] for p in poses] == [[[-1.0] * 3] * 2, [[-2.0] * 3] * 2, None]
    assert [p["gt"] for p in poses] == [None, [[9.0] * 3] * 2, None]
    assert [p["events"] for p in poses] == [5, 0, 2]
    for p in poses:
        assert p["window_end_wall_ms"] == 100_000.0 and p["sent_wall_ms"] == pytest.approx(100_010.0)
        assert p["step_ms"] == pytest.approx(3.0) and p["compare_step_ms"] == pytest.approx(4.0)
    stats = engine.stats
    assert (stats.poses, stats.events, stats.passes, stats.late_ticks) == (3, 14, 1, 0)
    for histogram, value in ((stats.step_ms, 3.0), (stats.compare_step_ms, 4.0), (stats.ready_latency_ms, 10.0)):
        assert histogram.count == 3 and (histogram.min, histogram.max) == pytest.approx((value, value))
    assert list(stats.recent_step_ms) == pytest.approx([3.0, 3.0, 3.0])
    # Both graphs saw both ticks, the main graph keeps its frames, the compare graph does not.
    main, cmp = ScriptedGraph.made
    assert (main.session, main.keep_frames, cmp.session, cmp.keep_frames) == ("main-session", True, "cmp-session", False)
    assert main.window_ms == WINDOW_MS and main.sensor_hw == (4, 6)
    assert len(main.ticks) == len(cmp.ticks) == 2 and main.closed == cmp.closed == 1 and source.closed == 1
    assert hub.of("frame") == []  # no client open


def test_without_a_compare_graph_the_messages_carry_none() -> None:
    clock = ManualClock()
    ScriptedGraph.scripts[True] = [([estimate(20_000, 1.0)], 0.002)]
    hub = Hub(clients=0)
    engine = engine_for(Source(clock, [(5.0, tick(5_000.0))]), hub, clock)
    asyncio.run(engine.run())
    (pose,) = hub.of("pose")
    assert pose["compare"] is None and pose["compare_step_ms"] is None and pose["gt"] is None
    assert pose["step_ms"] == pytest.approx(2.0) and engine.stats.compare_step_ms.count == 0
    assert len(ScriptedGraph.made) == 1


def test_a_tick_is_late_when_its_poses_go_out_more_than_one_window_after_it() -> None:
    """Exactly one window late is on time; a microsecond more is late; a tick without poses is
    never counted."""
    clock = ManualClock()
    ScriptedGraph.scripts[True] = [([estimate(20_000, 1.0)], 0.001), ([estimate(40_000, 1.0)], 0.001), ([], 0.0),
                                   ([estimate(60_000, 1.0)], 0.001)]
    ticks = [(1.020, tick(1_000.0)), (2.020_001, tick(2_000.0)), (9.0, tick(3_000.0)), (9.0, tick(4_000.0))]
    engine = engine_for(Source(clock, ticks), Hub(clients=0), clock)
    asyncio.run(engine.run())
    assert engine.stats.late_ticks == 2 and engine.stats.poses == 3


def test_a_new_pass_gets_fresh_graphs_a_status_and_its_time_offset() -> None:
    clock = ManualClock()
    lnes = np.ones((2, 2, 2), np.float32)
    ScriptedGraph.scripts[True] = [([estimate(20_000, 1.0)], 0.001), ([estimate(20_000, 5.0, lnes=lnes)], 0.001)]
    hub = Hub(clients=1)
    ticks = [(1.0, tick(1_000.0, pass_index=0)), (2.0, tick(2_000.0, pass_index=1))]
    engine = engine_for(Source(clock, ticks), hub, clock)
    asyncio.run(engine.run())
    first, second = ScriptedGraph.made
    assert first.closed == 1 and second.closed == 1 and len(first.ticks) == len(second.ticks) == 1
    assert [p["t_us"] for p in hub.of("pose")] == [20_000, 1_020_000] and [p["seq"] for p in hub.of("pose")] == [0, 1]
    assert hub.of("status") == [{"type": "status", "state": "loop",
                                 "message": "recording restarted (pass 2), fresh state"}]
    assert [kind for kind, _ in hub.sent if kind != "stats"] == ["pose", "status", "pose", "frame"]
    assert [(f["seq"], f["t_us"]) for f in hub.of("frame")] == [(1, 1_020_000)]  # the frame in the pass's time too
    assert engine.stats.passes == 2


def test_a_live_source_ends_with_a_finishing_tick_at_the_clocks_time() -> None:
    clock = ManualClock()
    ScriptedGraph.scripts[True] = [([], 0.0), ([estimate(20_000, 3.0)], 0.001)]
    hub = Hub(clients=0)
    source = Source(clock, [(1.0, tick(1_000.0, events=4))], live=True)
    engine = engine_for(source, hub, clock)
    assert asyncio.run(engine.run()) == "source stopped"
    last = ScriptedGraph.made[0].ticks[-1]
    assert (last.chunk, last.flush_until_us, last.finish, last.wall_ms, last.pass_index) == (None, None, True, 1_000.0, 0)
    assert hub.of("pose")[0]["window_end_wall_ms"] == 1_000.0


def test_frames_go_out_at_most_at_frame_hz_to_open_clients_after_the_pose() -> None:
    """frame_hz 10: one frame per 100 ms of wall time, the tick's last pose's window; none
    without its LNES or without an open client."""
    clock = ManualClock()
    lnes = np.zeros((2, 4, 8), np.float32)
    lnes[0, 1, 2] = 0.5
    script = [([estimate(20_000, 1.0, lnes=lnes), estimate(40_000, 2.0, lnes=lnes)], 0.002),  # t 0: frame
              ([estimate(60_000, 1.0, lnes=lnes)], 0.001),  # t 99.9 ms: too soon
              ([estimate(80_000, 1.0, lnes=lnes)], 0.001),  # t 100 ms: frame
              ([estimate(100_000, 1.0)], 0.001),  # t 300 ms, no LNES
              ([estimate(120_000, 1.0, lnes=lnes)], 0.001)]  # t 400 ms, no client open
    ScriptedGraph.scripts[True] = script
    hub = Hub(clients=1)

    class ClosingSource(Source):
        async def ticks(self):
            async for t in super().ticks():
                hub.clients = 0 if t.wall_ms == 4.0 else 1
                yield t
    ticks = [(0.0, tick(0.0)), (0.0999, tick(1.0)), (0.1, tick(2.0)), (0.3, tick(3.0)), (0.4, tick(4.0))]
    engine = engine_for(ClosingSource(clock, ticks), hub, clock)
    asyncio.run(engine.run())
    frames = hub.of("frame")
    assert [(f["seq"], f["t_us"]) for f in frames] == [(1, 40_000), (3, 80_000)]
    assert (frames[0]["width"], frames[0]["height"], frames[0]["channels"]) == (4, 2, 2)  # 8 columns over max_width 4
    assert frames[0] == json.loads(protocol.frame(seq=1, t_us=40_000, lnes=lnes, max_width=4))
    kinds = [kind for kind, _ in hub.sent if kind != "stats"]
    assert kinds[:3] == ["pose", "pose", "frame"]


def test_stats_go_out_once_per_period_with_the_last_seconds_figures() -> None:
    """The interval clock decides when (first at once, then after each full period); the wall
    clock which poses count for server_hz (sent within the last 1000 ms, inclusive)."""
    wall, interval = ManualClock(), ManualClock()
    ScriptedGraph.scripts[True] = [([estimate(20_000, 1.0)], 0.004), ([estimate(40_000, 1.0)], 0.002),
                                   ([estimate(60_000, 1.0)], 0.009), ([], 0.0)]

    class TimedSource(Source):
        async def ticks(self):
            for (at, t), (iv) in zip(self.script, (10.0, 10.5, 11.0, 11.0)):
                self.clock.now, interval.now = at, iv
                yield t
    hub = Hub(clients=3)
    ticks = [(100.0, tick(1.0)), (100.5, tick(2.0)), (101.0, tick(3.0)), (101.0001, tick(4.0))]
    engine = engine_for(TimedSource(wall, ticks), hub, wall, stats_period_s=1.0, interval=interval)
    asyncio.run(engine.run())
    stats = hub.of("stats")
    assert stats == [{"poses": 1, "server_hz": 1, "step_ms": pytest.approx(4.0), "clients": 3, "passes": 1},
                     {"poses": 3, "server_hz": 3, "step_ms": pytest.approx(4.0), "clients": 3, "passes": 1}]
    # The last tick (no poses, same interval time) sends none: the period has not passed.


def test_server_hz_leaves_out_poses_older_than_a_second_and_step_ms_is_the_recent_median() -> None:
    wall, interval = ManualClock(), ManualClock()
    engine = engine_for(Source(wall, []), Hub(clients=0), wall, interval=interval)
    hub = engine.hub
    engine._recent_wall.extend([1_000.0, 1_500.0, 2_000.0])
    engine.stats.recent_step_ms.extend([1.0, 9.0, 2.0, 3.0])
    wall.now, interval.now = 2.0, 50.0
    engine._maybe_stats()
    assert hub.of("stats")[-1]["server_hz"] == 3 and hub.of("stats")[-1]["step_ms"] == pytest.approx(2.5)
    interval.now = 51.0
    wall.now = 2.0000001
    engine._maybe_stats()
    assert hub.of("stats")[-1]["server_hz"] == 2  # exactly 1000 ms old counted; a little older does not
    # Any rate counts in full (a replay at --speed 10 of 20 ms windows makes 500 poses a second),
    # and what is older than a second is forgotten, so the count never holds more than a second.
    engine._recent_wall.extend([2_000.0] * 500)
    interval.now = 52.0
    engine._maybe_stats()
    assert hub.of("stats")[-1]["server_hz"] == 502
    wall.now, interval.now = 3.0005, 53.0
    engine._maybe_stats()
    assert hub.of("stats")[-1]["server_hz"] == 0 and len(engine._recent_wall) == 0
    fresh = engine_for(Source(wall, []), Hub(clients=0), wall, interval=ManualClock(0.0))
    fresh._maybe_stats()
    assert fresh.hub.of("stats") == [{"poses": 0, "server_hz": 0, "step_ms": None, "clients": 0, "passes": 1}]


def test_server_hz_is_the_poses_sent_within_the_last_second() -> None:
    """Poses sent at 2 ms intervals for 1.5 s (750): the stats message counts the 501 sent in the
    last second, ends included; the engine keeps no more than that second."""
    clock = ManualClock()
    ScriptedGraph.scripts[True] = [([estimate(20_000 * (k + 1), 1.0)], 0.001) for k in range(750)]
    ticks = [(10.0 + 0.002 * k, tick(1e4 + 2.0 * k)) for k in range(750)]
    hub = Hub(clients=0)
    engine = engine_for(Source(clock, ticks), hub, clock, interval=ManualClock(0.0), stats_period_s=1e9)
    asyncio.run(engine.run())
    assert len(engine._recent_wall) <= 501
    engine.stats_period_s, clock.now = 0.0, 10.0 + 0.002 * 749
    engine._maybe_stats()
    assert hub.of("stats")[-1]["server_hz"] == 501


def test_the_recent_step_median_covers_the_last_recent_steps_only() -> None:
    clock = ManualClock()
    ScriptedGraph.scripts[True] = [([estimate(20_000 * (k + 1), 1.0)], 0.001 * (100 if k == 0 else 1))
                                   for k in range(RECENT_STEPS + 1)]
    ticks = [(float(k), tick(1e3 * k)) for k in range(RECENT_STEPS + 1)]
    engine = engine_for(Source(clock, ticks), Hub(clients=0), clock)
    asyncio.run(engine.run())
    # docs/serve.md: "median step time of the last 50 windows".
    assert len(engine.stats.recent_step_ms) == 50 == RECENT_STEPS and max(engine.stats.recent_step_ms) == pytest.approx(1.0)
    assert engine.stats.step_ms.count == RECENT_STEPS + 1


# -- the real per-graph worker on the toy graph -------------------------------------------------------
@pytest.fixture(scope="module")
def toy_graph(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("toy") / "toy.onnx"
    onnx.save(toy_step_graph(), path)
    return path


def test_the_graph_worker_pushes_flushes_and_finishes_a_tick(toy_graph) -> None:
    """The toy's pose is 2 s' with s' = s + window_s + sum(LNES): one window closed by the
    flush, its pose written out in numpy; the runtime seconds are what the estimator counted."""
    from e3dpsm.runtime import StepSession

    graph = _Graph(StepSession(toy_graph, threads=1), WINDOW_MS, (2, 3), keep_frames=True)
    try:
        events = (np.array([1, 2]), np.array([0, 1]), np.array([0, 10_000], np.int64), np.array([1, 0]))
        poses, seconds = asyncio.run(graph.run(Tick(events, None, False, 0.0, 0)))
        assert poses == [] and seconds == 0.0
        poses, seconds = asyncio.run(graph.run(Tick(None, WINDOW_US, False, 0.0, 0)))
        (pose,) = poses
        assert pose.t_us == WINDOW_US and pose.events == 2 and pose.lnes is not None
        first_state = toy_numpy_step(pose.lnes[None], np.asarray([INIT]), WINDOW_MS)
        np.testing.assert_allclose(pose.pose, 2 * first_state[0], rtol=1e-6)
        assert seconds == pytest.approx(graph.estimator.stats.step_seconds) and seconds > 0
        # A chunk and the end in one tick: the event on the window's last microsecond closes it, and
        # the state carries over from the first window.
        later = (np.array([0]), np.array([0]), np.array([2 * WINDOW_US - 1], np.int64), np.array([1]))
        (second,) = asyncio.run(graph.run(Tick(later, None, True, 0.0, 0)))[0]
        assert second.t_us == 2 * WINDOW_US and second.events == 1 and second.lnes.sum() > 0
        np.testing.assert_allclose(second.pose, 2 * toy_numpy_step(second.lnes[None], first_state, WINDOW_MS)[0],
                                   rtol=1e-6)
        assert asyncio.run(graph.run(Tick(None, None, True, 0.0, 0))) == ([], 0.0)
    finally:
        graph.close()
    with pytest.raises(RuntimeError):
        graph.worker.submit(lambda: None)


def _events(*t_us: int) -> tuple[np.ndarray, ...]:
    n = len(t_us)
    return (np.arange(n) % 3, np.arange(n) % 2, np.array(t_us, np.int64), np.arange(n) % 2)


@pytest.mark.parametrize("closing", ["flush", "finish"])
def test_one_tick_gives_the_windows_its_events_complete_and_those_it_closes(toy_graph, closing) -> None:
    """Events in windows 0 and 1: the chunk itself completes window 0 (an event past its end),
    the tick's flush or finish closes window 1; the tick returns both poses."""
    from e3dpsm.runtime import StepSession

    graph = _Graph(StepSession(toy_graph, threads=1), WINDOW_MS, (2, 3), keep_frames=False)
    try:
        chunk = _events(0, 10_000, 25_000, 2 * WINDOW_US - 1)
        flush = 2 * WINDOW_US if closing == "flush" else None
        poses, seconds = asyncio.run(graph.run(Tick(chunk, flush, closing == "finish", 0.0, 0)))
        assert [p.t_us for p in poses] == [WINDOW_US, 2 * WINDOW_US] and [p.events for p in poses] == [2, 2]
        assert seconds == pytest.approx(graph.estimator.stats.step_seconds) and poses[0].lnes is None
    finally:
        graph.close()


def test_closing_a_graph_never_waits_for_its_step_and_drops_queued_work(toy_graph) -> None:
    """A new pass or the end of a session closes graphs from the event loop: it must not block
    on a step in flight, and work queued behind it is cancelled."""
    import threading
    import time

    from e3dpsm.runtime import StepSession

    graph = _Graph(StepSession(toy_graph, threads=1), WINDOW_MS, (2, 3), keep_frames=False)
    release, started = threading.Event(), threading.Event()
    running = graph.worker.submit(lambda: (started.set(), release.wait(10)))
    queued = graph.worker.submit(lambda: "never")
    assert started.wait(5)
    began = time.perf_counter()
    graph.close()
    assert time.perf_counter() - began < 1.0 and not running.done()
    assert queued.cancelled()
    release.set()
    assert running.result(timeout=5)[1] is True


def test_the_engine_steps_a_real_graph_with_the_documented_defaults(toy_graph) -> None:
    """ServeEngine with its own graphs (not scripted) over the toy: the poses the toy computes,
    in order, with the state carried; frames at most 128 columns and stats about once a second
    (docs/serve.md)."""
    from e3dpsm.runtime import StepSession

    clock = ManualClock()

    class ToySource(Source):
        sensor_hw = (2, 3)
    ticks = [(0.01, Tick(_events(0, 10_000, 25_000), None, False, 10.0, 0)),
             (0.05, Tick(_events(45_000), 2 * WINDOW_US, False, 50.0, 0))]
    hub = Hub(clients=0)
    engine = ServeEngine(ToySource(clock, ticks), hub, StepSession(toy_graph, threads=1), window_ms=WINDOW_MS,
                         wall_clock=clock, interval_clock=clock)
    assert (engine.frame_max_width, engine.stats_period_s, engine.window_us) == (128, 1.0, WINDOW_US)
    assert asyncio.run(engine.run()) == "recording ended"
    poses = hub.of("pose")
    assert [p["t_us"] for p in poses] == [WINDOW_US, 2 * WINDOW_US] and [p["events"] for p in poses] == [2, 1]
    first, second = (np.asarray(p["pose"], np.float64) for p in poses)
    # pose = 2 s'; s' = s + window_s + sum(LNES); the second step starts from the first's state.
    assert np.all(first > 2 * (np.asarray(INIT) + WINDOW_MS / 1e3)) and np.ptp(first - 2 * np.asarray(INIT)) < 1e-3
    step = second - first
    assert np.ptp(step) < 1e-3 and step[0] > 2 * WINDOW_MS / 1e3  # the same increment for every element
