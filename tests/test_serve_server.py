"""One serving session (serve/server.py) in this process: a scripted engine and source, the real
app and client hub, so each way a session ends is checked for its reason, the status the pages
get, and the report it writes; and the session's small pieces (config, socket, URL, RSS)."""
from __future__ import annotations

import asyncio
import dataclasses
import json
import re
import signal
import socket
from pathlib import Path
from typing import Any

import pytest

from _timing_helpers import ManualClock
from e3dpsm.errors import ConfigError
from e3dpsm.serve import protocol
from e3dpsm.serve import server as server_module
from e3dpsm.serve.clients import ClientHub
from e3dpsm.serve.estimator import EngineStats
from e3dpsm.serve.report import REPORT_NAME
from e3dpsm.serve.server import (MAX_RSS_SAMPLES, ServeConfig, _replay, _RssSampler, _wait_for_clients,
                                 listen_socket, page_url, serve)


# -- the pieces --------------------------------------------------------------------------------------
def test_the_config_in_the_report_never_holds_the_token() -> None:
    config = ServeConfig(model="m.onnx", source="r.h5", out="o", token="s3cret", allow_origins=("http://a:1",))
    written = config.for_report()
    assert written["token"] == "(set)" and written["allow_origins"] == ["http://a:1"]
    assert "s3cret" not in json.dumps(written)
    assert ServeConfig(model="m", source="s", out="o").for_report()["token"] is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.token = "other"  # a session's settings do not change under it
    assert {k: v for k, v in written.items() if k not in ("token", "allow_origins")} == {
        "model": "m.onnx", "source": "r.h5", "out": "o", "host": "127.0.0.1", "port": 8765, "speed": 1.0,
        "compare": None, "threads": None, "window_ms": None, "duration_s": None, "loop": False, "wait_clients": 0,
        "client_backlog": 250, "frame_hz": 10.0}


def test_the_listening_socket_is_bound_non_blocking_and_listening() -> None:
    sock = listen_socket("127.0.0.1", 0)
    try:
        host, port = sock.getsockname()
        assert host == "127.0.0.1" and port > 0 and sock.family == socket.AF_INET
        assert not sock.getblocking() and sock.getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN) == 1
        assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR) != 0
        client = socket.create_connection(("127.0.0.1", port), timeout=5)  # the backlog takes it before accept
        client.close()
        # A name with IPv4 and IPv6 addresses gets the IPv4 one.
        with listen_socket("localhost", 0) as named:
            assert named.family == socket.AF_INET
        with pytest.raises(ConfigError, match=rf"^cannot listen on 127\.0\.0\.1:{port}: Address already in use$"):
            listen_socket("127.0.0.1", port)  # taken by the first
    finally:
        sock.close()
    with pytest.raises(ConfigError, match=r"^cannot listen on no-such-host\.invalid:0: [^\[]") as refused:
        listen_socket("no-such-host.invalid", 0)
    assert "Errno" not in str(refused.value)  # the system's words, not Python's repr of the error


def test_a_name_with_both_families_listens_on_ipv4(monkeypatch) -> None:
    """getaddrinfo lists IPv6 first on many systems; the socket takes the IPv4 address."""
    real = socket.getaddrinfo
    v4 = real("127.0.0.1", 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    v6 = [(socket.AF_INET6, socket.SOCK_STREAM, 6, "", ("::1", 0, 0, 0))]
    monkeypatch.setattr(socket, "getaddrinfo", lambda *args, **kwargs: v6 + v4)
    with listen_socket("both.example", 0) as sock:
        assert sock.family == socket.AF_INET and sock.getsockname()[0] == "127.0.0.1"


def test_the_page_url_names_a_host_others_can_reach_and_carries_the_token(monkeypatch) -> None:
    monkeypatch.setattr(socket, "gethostname", lambda: "box")
    config = lambda **kw: ServeConfig(model="m", source="s", out="o", **kw)  # noqa: E731
    assert page_url(config(token="t0k"), 8123) == "http://127.0.0.1:8123/?token=t0k"
    assert page_url(config(), 80) == "http://127.0.0.1:80/"
    for wildcard in ("", "0.0.0.0", "::"):
        assert page_url(config(host=wildcard, token="t"), 9) == "http://box:9/?token=t"
    assert page_url(config(host="::1", token="t"), 9) == "http://[::1]:9/?token=t"


class Memory:
    readings: list[float] = []

    def __init__(self) -> None:
        self.rss = Memory.readings.pop(0)


def test_the_rss_samples_are_bounded_and_summarised(monkeypatch) -> None:
    """Seconds since the sampler began and MB, two decimals each; at most MAX_RSS_SAMPLES."""
    monkeypatch.setattr(server_module, "MAX_RSS_SAMPLES", 3)
    clock = ManualClock(50.0)
    rss = _RssSampler(clock)
    assert rss.summary() == {"start": None, "end": None, "max": None, "period_s": 1.0, "samples": []}
    Memory.readings = [100.123456 * 2**20, 300.5 * 2**20, 200.004 * 2**20, 999 * 2**20]
    monkeypatch.setattr(rss.process, "memory_info", Memory)
    for _ in range(5):
        clock.advance(1.23456)
        rss.sample()
    summary = rss.summary()
    assert summary["samples"] == [[1.23, 100.12], [2.47, 300.5], [3.7, 200.0]]  # the fourth reading is never taken
    assert (summary["start"], summary["end"], summary["max"]) == (100.12, 200.0, 300.5)
    assert MAX_RSS_SAMPLES == 7200 and len(Memory.readings) == 1


def test_the_rss_sampler_samples_every_period_until_cancelled(monkeypatch) -> None:
    monkeypatch.setattr(server_module, "RSS_PERIOD_S", 0.01)

    async def scenario() -> int:
        rss = _RssSampler()
        task = asyncio.create_task(rss.run())
        await asyncio.sleep(0.2)
        task.cancel()
        return len(rss.samples)
    assert asyncio.run(scenario()) >= 3


class Hub:
    def __init__(self) -> None:
        self.seen, self.connected, self.statuses = 0, asyncio.Event(), []

    def set_status(self, text: str) -> None:
        self.statuses.append(json.loads(text))


def test_waiting_for_clients_ends_when_enough_came_or_on_stop() -> None:
    async def scenario(arrivals: int, stop_after: float | None) -> tuple[bool, Hub]:
        hub, stop = Hub(), asyncio.Event()

        async def arrive() -> None:
            for _ in range(arrivals):
                await asyncio.sleep(0.01)
                hub.seen += 1
                hub.connected.set()
        tasks = [asyncio.create_task(arrive())]
        if stop_after is not None:
            tasks.append(asyncio.create_task(asyncio.sleep(stop_after)))
            tasks[-1].add_done_callback(lambda _: stop.set())
        result = await asyncio.wait_for(_wait_for_clients(hub, 2, stop), 10)
        for task in tasks:
            task.cancel()
        return result, hub
    came, hub = asyncio.run(scenario(3, None))
    assert came and hub.seen == 2  # returns on the second client, not later
    assert hub.statuses == [{"type": "status", "state": "waiting",
                             "message": "waiting for 2 client(s) before the replay starts"}]
    came, hub = asyncio.run(scenario(1, 0.05))
    assert not came and hub.seen == 1


class Engine:
    """Scripted `run`: a reason, an exception, or a wait for ever (until cancelled)."""

    def __init__(self, outcome: str | BaseException | None) -> None:
        self.outcome, self.stats, self.cancelled, self.started = outcome, EngineStats(), False, False

    async def run(self) -> str:
        self.started = True
        try:
            if self.outcome is None:
                await asyncio.sleep(3600)
            if isinstance(self.outcome, BaseException):
                raise self.outcome
            return self.outcome
        except asyncio.CancelledError:
            self.cancelled = True
            raise


class Source:
    def __init__(self, live: bool = False, stop_message: str | None = None) -> None:
        self.live, self.closed = live, 0
        if stop_message is not None:
            self.stop_message = stop_message

    def close(self) -> None:
        self.closed += 1


def replay(config: ServeConfig, source: Source, engine: Engine, stop_after: float | None = None) -> tuple[str, Hub]:
    async def scenario() -> str:
        hub, stop = Hub(), asyncio.Event()
        if stop_after is not None:
            asyncio.get_running_loop().call_later(stop_after, stop.set)
        return await asyncio.wait_for(_replay(config, source, engine, hub, stop), 10), hub
    return asyncio.run(scenario())


CONFIG = ServeConfig(model="m.onnx", source="/data/rec/walk.h5", out="o", speed=2.5)


@pytest.mark.parametrize("source, outcome, status", [
    (Source(), "recording ended", ("recording ended", "the recording ended; the server stops")),
    (Source(live=True), "source stopped", ("source stopped", "the live source stopped")),
    (Source(live=True, stop_message="dv://cam: the publisher stopped"), "source stopped",
     ("source stopped", "dv://cam: the publisher stopped")),
])
def test_replay_ends_with_the_engine_and_tells_the_pages_why(source, outcome, status) -> None:
    reason, hub = replay(CONFIG, source, Engine(outcome))
    assert reason == outcome
    running = "recording walk.h5 at 2.5x" if not source.live else "live source /data/rec/walk.h5"
    assert [(s["state"], s["message"]) for s in hub.statuses] == [("running", running), status]


def test_replay_stops_on_ctrl_c_or_the_duration_and_cancels_the_engine() -> None:
    engine = Engine(None)
    reason, hub = replay(CONFIG, Source(), engine, stop_after=0.05)
    assert reason == "interrupted" and engine.cancelled
    assert hub.statuses[-1] == {"type": "status", "state": "stopping", "message": "the server stops (Ctrl-C)"}
    engine = Engine(None)
    reason, hub = replay(ServeConfig(model="m", source="s", out="o", duration_s=0.05), Source(), engine)
    assert reason == "duration" and engine.cancelled
    assert hub.statuses[-1]["message"] == "the server stops (--duration-s 0.05)"
    # The engine ending first wins over a later duration.
    reason, _ = replay(ServeConfig(model="m", source="s", out="o", duration_s=5.0), Source(), Engine("recording ended"))
    assert reason == "recording ended"


def test_replay_raises_what_the_engine_raised() -> None:
    with pytest.raises(ValueError, match="bad window"):
        replay(CONFIG, Source(), Engine(ValueError("bad window")))


# -- whole sessions in this process ---------------------------------------------------------------
def session(tmp_path: Path, engine: Engine, source: Source, *, interrupt_when: Any = None,
            **config: Any) -> tuple[dict[str, Any] | BaseException, list[str], ClientHub]:
    """serve() to its end; `interrupt_when(hub)`: once it holds, what a SIGINT does (the stop
    event set), with the signal's handler checked to be the session's. No real signal is sent
    in this process: in a pytest-xdist worker of the full suite one ended the worker (2026-12-05,
    not reproduced alone); tests/test_serve.py sends real ones to a server process."""
    config = ServeConfig(model="m.onnx", source="rec.h5", out=str(tmp_path / "report"), port=0,
                         **{"token": "tok-123", **config})
    hub, lines = ClientHub(config.client_backlog), []

    async def scenario() -> dict[str, Any]:
        stop = asyncio.Event()
        if interrupt_when is not None:
            async def interrupt() -> None:
                while not interrupt_when(hub):
                    await asyncio.sleep(0.01)
                handlers.append(signal.getsignal(signal.SIGINT))
                stop.set()
            watcher = asyncio.create_task(interrupt())  # noqa: F841 - ends with the loop
        return await asyncio.wait_for(serve(config, source, engine, hub, {"joints": []}, {"m": {"path": "m.onnx"}},
                                            announce=lines.append, stop=stop), 30)
    handlers: list[Any] = []
    before = signal.getsignal(signal.SIGINT)
    try:
        result: dict[str, Any] | BaseException = asyncio.run(scenario())
    except Exception as exc:  # noqa: BLE001 - the test reads it
        result = exc
    # While the session ran, SIGINT was the session's (asyncio's handler, not Python's own);
    # after it, the handler is what it was.
    assert all(handler not in (before, signal.SIG_DFL, signal.SIG_IGN) for handler in handlers)
    assert signal.getsignal(signal.SIGINT) is before
    return result, lines, hub


@pytest.fixture
def endings(monkeypatch) -> list[tuple[str, Any]]:
    """What the session handed to drain_clients (its timeout) and close_all (code, reason);
    both still run."""
    seen: list[tuple[str, Any]] = []
    drain, close = server_module.drain_clients, server_module.close_all

    async def recorded_drain(hub, timeout_s):
        seen.append(("drain", timeout_s))
        await drain(hub, timeout_s)

    async def recorded_close(app, code, reason):
        seen.append(("close", (code, reason)))
        await close(app, code, reason)
    monkeypatch.setattr(server_module, "drain_clients", recorded_drain)
    monkeypatch.setattr(server_module, "close_all", recorded_close)
    return seen


@pytest.mark.parametrize("outcome, drain_s", [("recording ended", 1.0), ("source stopped", 1.0), (None, 0.2)])
def test_clients_get_a_second_to_drain_at_the_end_of_a_source_and_less_on_a_stop(tmp_path, endings, outcome,
                                                                                  drain_s) -> None:
    engine = Engine(outcome)
    interrupt = None if outcome else (lambda hub: engine.started)
    report, _, _ = session(tmp_path, engine, Source(live=outcome == "source stopped"), interrupt_when=interrupt)
    assert endings == [("drain", drain_s), ("close", (protocol.CLOSE_GOING_AWAY, report["stop_reason"]))]


def test_the_close_reason_is_cut_to_100_characters(tmp_path, endings) -> None:
    """A WebSocket close frame holds at most 123 bytes of reason."""
    error, _, _ = session(tmp_path, Engine(RuntimeError("x" * 300)), Source())
    assert isinstance(error, RuntimeError)
    (code, reason), = [value for kind, value in endings if kind == "close"]
    assert code == protocol.CLOSE_GOING_AWAY and reason == ("error: " + "x" * 300)[:100] and len(reason) == 100


def test_a_session_announces_its_url_and_writes_its_report(tmp_path) -> None:
    source, engine = Source(), Engine("recording ended")
    engine.stats.poses = 7
    report, lines, hub = session(tmp_path, engine, source)
    (line,) = lines
    port = re.match(r"^serving http://127\.0\.0\.1:(\d+)/\?token=tok-123 \(Ctrl-C stops; report -> ", line)
    assert port and 0 < int(port.group(1)) < 65536  # the port it was bound to (--port 0)
    assert line.endswith(f"{tmp_path / 'report' / REPORT_NAME})")
    written = json.loads((tmp_path / "report" / REPORT_NAME).read_text())
    assert written == json.loads(json.dumps(report))
    assert report["stop_reason"] == "recording ended" and report["poses"] == 7 and report["graphs"] == {"m": {"path": "m.onnx"}}
    assert report["config"]["token"] == "(set)" and report["config"]["port"] == 0
    assert report["rss_mb"]["start"] > 0 and len(report["rss_mb"]["samples"]) >= 2  # at the start and at the end
    assert source.closed == 1 and hub.status is not None and json.loads(hub.status)["state"] == "recording ended"
    assert [p.name for p in (tmp_path / "report").iterdir()] == [REPORT_NAME]  # nothing half-written beside it


def test_a_session_without_a_token_says_so(tmp_path) -> None:
    _, lines, _ = session(tmp_path, Engine("recording ended"), Source(), token=None)
    assert "/ (no token: --no-token, loopback only; Ctrl-C stops; report -> " in lines[0]
    assert "?token=" not in lines[0]


def test_an_engine_error_reaches_the_pages_the_report_and_the_caller(tmp_path) -> None:
    source = Source()
    error, _, hub = session(tmp_path, Engine(RuntimeError("step failed")), source)
    assert isinstance(error, RuntimeError) and str(error) == "step failed"
    assert json.loads(hub.status) == {"type": "status", "state": "stopping", "message": "stopped by an error: step failed"}
    written = json.loads((tmp_path / "report" / REPORT_NAME).read_text())
    assert written["stop_reason"] == "error: step failed" and source.closed == 1


def test_a_stop_while_waiting_for_clients_ends_the_session_as_interrupted(tmp_path) -> None:
    engine = Engine("recording ended")
    report, _, hub = session(tmp_path, engine, Source(), wait_clients=1, interrupt_when=lambda hub: hub.status)
    assert report["stop_reason"] == "interrupted" and hub.seen == 0 and not engine.started
    assert json.loads(hub.status)["state"] == "waiting"  # the replay never started


def test_the_session_puts_back_the_signal_handlers_it_found(tmp_path) -> None:
    """An application embedding serve() keeps its own SIGINT and SIGTERM handlers afterwards
    (asyncio alone would put Python's defaults back)."""
    def mine(signum, frame):  # pragma: no cover - never called
        raise AssertionError("not to be called")
    old = {sig: signal.signal(sig, handler) for sig, handler in ((signal.SIGINT, signal.SIG_IGN),
                                                                  (signal.SIGTERM, mine))}
    try:
        report, _, _ = session(tmp_path, Engine("recording ended"), Source())
        assert report["stop_reason"] == "recording ended"
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN and signal.getsignal(signal.SIGTERM) is mine
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def test_a_stop_during_the_replay_ends_it(tmp_path) -> None:
    engine = Engine(None)
    report, _, hub = session(tmp_path, engine, Source(), interrupt_when=lambda hub: engine.started)
    assert report["stop_reason"] == "interrupted" and engine.cancelled
    assert json.loads(hub.status)["message"] == "the server stops (Ctrl-C)"


def test_a_refused_no_token_host_leaves_no_socket_open(tmp_path, monkeypatch) -> None:
    opened: list[socket.socket] = []
    real = server_module.listen_socket
    monkeypatch.setattr(server_module, "listen_socket", lambda host, port: opened.append(real(host, port)) or opened[-1])
    error, lines, _ = session(tmp_path, Engine("recording ended"), Source(), token=None, host="0.0.0.0")
    assert isinstance(error, ConfigError) and "loopback only" in str(error)
    assert lines == [] and opened[0].fileno() == -1 and not (tmp_path / "report").exists()
