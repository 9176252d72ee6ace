"""`e3dpsm run`'s live form (runtime/run_live.py) on a scripted source: the same poses and CSV
as the one-file form, the report's `live` section, why it stopped, the refusal when no window
closes, and the chunk loop's deadline (an injected clock) and gap check across chunks.
tests/test_live.py runs it against dv-processing's own publisher."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _runtime_helpers import exported_tiny, synthetic_stream
from _timing_helpers import ManualClock
from e3dpsm.data import live as live_module
from e3dpsm.data.readers import read_events
from e3dpsm.data.sequence import EventStream
from e3dpsm.errors import DataError
from e3dpsm.runtime.run_command import LIVE_TIMEOUT_S, RunRequest, run_poses
from e3dpsm.runtime.run_live import _chunks

URL = "dv://127.0.0.1:7777"


class ScriptedSource:
    """A LiveEventSource's surface: yields the given chunks, counts their events, then says why
    it stopped; each chunk advances `clock` (when given) by a second."""

    def __init__(self, chunks: list[EventStream], stopped_reason: str | None, sensor_hw=None, clock=None) -> None:
        self.url, self.sensor_hw, self.events = URL, sensor_hw, 0
        self.chunks, self.final_reason, self.clock = chunks, stopped_reason, clock
        self.stopped_reason: str | None = None

    def __enter__(self) -> "ScriptedSource":
        return self

    def __exit__(self, *exc) -> None:
        return None

    def __iter__(self):
        for chunk in self.chunks:
            self.events += len(chunk)
            if self.clock is not None:
                self.clock.advance(1.0)
            yield chunk
        self.stopped_reason = self.final_reason


def _split(stream: EventStream, cuts: list[int]) -> list[EventStream]:
    edges = [0, *cuts, len(stream)]
    return [EventStream(stream.x[a:b], stream.y[a:b], stream.t_us[a:b], stream.p[a:b], sensor_hw=stream.sensor_hw)
            for a, b in zip(edges[:-1], edges[1:])]


@pytest.fixture(scope="module")
def graph(tmp_path_factory) -> Path:
    return exported_tiny(str(tmp_path_factory.getbasetemp()))[1]


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    x, y, t, p = synthetic_stream(seed=3, windows=12)
    path = tmp_path_factory.mktemp("live_pieces") / "events.npz"
    np.savez(path, x=x, y=y, t=t, p=p)
    return path


def _serve(monkeypatch, source: ScriptedSource) -> list[tuple[str, float]]:
    opened: list[tuple[str, float]] = []

    def open_live_source(url: str, timeout_s: float) -> ScriptedSource:
        opened.append((url, timeout_s))
        return source

    monkeypatch.setattr(live_module, "open_live_source", open_live_source)
    return opened


def test_the_live_form_writes_what_the_file_form_writes(monkeypatch, graph, recording, tmp_path) -> None:
    stream = read_events(recording)
    reason = f"publisher {URL} closed the stream after {len(stream)} events"
    source = ScriptedSource(_split(stream, [1, 700, 701, 2500]), reason, sensor_hw=stream.sensor_hw)
    opened = _serve(monkeypatch, source)
    common = dict(model=str(graph), threads=1)
    filed = run_poses(RunRequest(**common, events=(str(recording),), out=tmp_path / "file.csv"))
    result = run_poses(RunRequest(**common, events=(URL,), out=tmp_path / "live.csv", live_timeout_s=2.5))
    assert opened == [(URL, 2.5)]
    assert (tmp_path / "live.csv").read_text() == (tmp_path / "file.csv").read_text()
    report = json.loads((tmp_path / "live.report.json").read_text())
    assert report == result.report and report["windows"] == filed.report["windows"] > 5
    assert report["live"] == {"url": URL, "events_received": len(stream), "stopped": reason, "max_seconds": None}
    assert result.summary == (f"{report['windows']} poses from {URL} ({len(stream)} events; {reason}) "
                              f"-> {tmp_path / 'live.csv'}",)


def test_a_source_that_ends_without_a_reason_ended_at_the_deadline(monkeypatch, graph, recording, tmp_path) -> None:
    stream = read_events(recording)
    opened = _serve(monkeypatch, ScriptedSource(_split(stream, [900]), None, sensor_hw=stream.sensor_hw))
    result = run_poses(RunRequest(model=str(graph), events=(URL,), out=tmp_path / "p.csv", threads=1, max_seconds=3.0))
    assert opened == [(URL, LIVE_TIMEOUT_S)]  # the request's default connect and silence bound
    assert result.report["live"]["stopped"] == "--max-seconds 3 reached"
    assert result.report["live"]["max_seconds"] == 3.0
    assert result.summary[0].endswith(f"({len(stream)} events; --max-seconds 3 reached) -> {tmp_path / 'p.csv'}")


def test_no_complete_window_is_one_line_and_nothing_written(monkeypatch, graph, recording, tmp_path) -> None:
    stream = read_events(recording)
    first = _split(stream, [5])[0]  # five events, well inside the first window
    reason = f"publisher {URL} closed the stream after 5 events"
    _serve(monkeypatch, ScriptedSource([first], reason, sensor_hw=stream.sensor_hw))
    with pytest.raises(DataError) as info:
        run_poses(RunRequest(model=str(graph), events=(URL,), out=tmp_path / "p.csv", threads=1))
    assert str(info.value) == f"{URL}: no complete 20 ms window before the stream ended ({reason}); nothing to estimate"
    assert list(tmp_path.iterdir()) == []


def _stream(*times_us: int) -> EventStream:
    t = np.asarray(times_us, np.int64)
    zeros = np.zeros(t.size, np.int32)
    return EventStream(zeros, zeros, t, zeros.astype(np.uint8), sensor_hw=(4, 4))


@pytest.mark.parametrize("max_seconds, yielded", [(None, 5), (2.5, 3), (3.0, 3), (3.5, 4), (0.5, 1)])
def test_the_chunk_loop_stops_at_the_first_chunk_at_or_past_the_deadline(max_seconds, yielded) -> None:
    clock = ManualClock(100.0)
    chunks = [_stream(10 * k, 10 * k + 5) for k in range(5)]
    source = ScriptedSource(chunks, None, clock=clock)
    got = list(_chunks(source, max_seconds, 60.0, 20.0, clock=clock))
    assert len(got) == yielded
    for (x, y, t, p), chunk in zip(got, chunks):
        assert t is chunk.t_us and x is chunk.x and y is chunk.y and p is chunk.p


def test_a_silence_across_chunks_is_refused_even_after_an_empty_chunk() -> None:
    chunks = [_stream(1_000, 2_000), _stream(), _stream(62_000_001, 62_000_002)]
    with pytest.raises(DataError) as info:
        list(_chunks(ScriptedSource(chunks, None), None, 60.0, 20.0))
    assert str(info.value) == (f"{URL}: event 0 and the event before it are 61.998 s apart: 3,100 empty 20 ms windows "
                               "to step. No event camera is silent that long: a timestamp is corrupted, or pass "
                               "--max-gap-s 62 to run it as it is")
    # Within the bound across the same boundary: every chunk passes.
    ok = [_stream(1_000, 2_000), _stream(), _stream(60_002_000)]
    assert len(list(_chunks(ScriptedSource(ok, None), None, 60.0, 20.0))) == 3
