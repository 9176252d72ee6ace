"""One serving session: bind, wait for clients if asked, replay, stop, write the report.

Stops on the first of: the end of the recording (without --loop), a live source stopping,
--duration-s of replay, SIGINT / SIGTERM. Every way out closes the clients with 1001 after
telling them why (a "status" message), and writes serve.report.json atomically.
"""
from __future__ import annotations

import asyncio
import signal
import socket
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

from e3dpsm.serve import protocol
from e3dpsm.serve.app import close_all, drain_clients, make_app
from e3dpsm.serve.clients import ClientHub
from e3dpsm.serve.estimator import ServeEngine
from e3dpsm.serve.report import build_report, report_path
from e3dpsm.serve.security import WILDCARD_HOSTS, Access, Refusals

DRAIN_S = 1.0  # at the end of a recording, how long clients get to receive what is queued
RSS_PERIOD_S = 1.0
MAX_RSS_SAMPLES = 7200
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # each ends a session cleanly (Ctrl-C, a service manager)


@dataclass(frozen=True)
class ServeConfig:
    model: str
    source: str
    out: str
    host: str = "127.0.0.1"
    port: int = 8765
    token: str | None = None  # None: no token (--no-token, loopback only)
    allow_origins: tuple[str, ...] = ()
    speed: float = 1.0
    compare: str | None = None
    threads: int | None = None
    window_ms: float | None = None
    duration_s: float | None = None
    loop: bool = False
    wait_clients: int = 0
    client_backlog: int = 250
    frame_hz: float = 10.0

    def for_report(self) -> dict[str, Any]:
        config = asdict(self)
        config["token"] = None if self.token is None else "(set)"  # never written to disk
        config["allow_origins"] = list(self.allow_origins)
        return config


def listen_socket(host: str, port: int) -> socket.socket:
    """A listening socket on `host`:`port` (an IPv4 address first when the name has both), bound
    before the app is built so that the app's rules know the real port (`--port 0`)."""
    from e3dpsm.errors import ConfigError

    try:
        infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        family, kind, proto, _, address = sorted(infos, key=lambda info: info[0] != socket.AF_INET)[0]
        sock = socket.socket(family, kind, proto)
    except OSError as exc:
        raise ConfigError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from exc
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(128)
        sock.setblocking(False)
    except OSError as exc:
        sock.close()
        raise ConfigError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from exc
    return sock


def page_url(config: ServeConfig, port: int) -> str:
    """The URL to open: bound to every interface, the machine's name (reachable from others)."""
    host = socket.gethostname() if config.host in WILDCARD_HOSTS else config.host
    host = f"[{host}]" if ":" in host else host
    return f"http://{host}:{port}/" + (f"?token={config.token}" if config.token else "")


class _RssSampler:
    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        import psutil

        self.process = psutil.Process()
        self.samples: list[tuple[float, float]] = []
        self.clock = clock
        self.began = clock()

    def sample(self) -> None:
        if len(self.samples) < MAX_RSS_SAMPLES:
            self.samples.append((round(self.clock() - self.began, 2),
                                 round(self.process.memory_info().rss / 2**20, 2)))

    async def run(self) -> None:
        while True:
            self.sample()
            await asyncio.sleep(RSS_PERIOD_S)

    def summary(self) -> dict[str, Any]:
        values = [mb for _, mb in self.samples]
        return {"start": values[0] if values else None, "end": values[-1] if values else None,
                "max": max(values) if values else None, "period_s": RSS_PERIOD_S,
                "samples": [list(s) for s in self.samples]}


async def serve(config: ServeConfig, source: Any, engine: ServeEngine, hub: ClientHub,
                hello_fields: dict[str, Any], graphs: dict[str, Any],
                announce: Callable[[str], None] = print, stop: asyncio.Event | None = None) -> dict[str, Any]:
    """Run the session to its end; returns the report (also written to `config.out`). SIGINT
    and SIGTERM set `stop` (a new event unless given: a caller may stop the session itself)."""
    from aiohttp import web

    from e3dpsm.utils.io import write_json_atomic

    rss = _RssSampler()
    rss.sample()
    sock = listen_socket(config.host, config.port)
    port = sock.getsockname()[1]  # the real one when --port 0
    try:
        access = Access.for_server(config.host, port, config.token, config.allow_origins)
    except Exception:
        sock.close()
        raise
    refusals = Refusals()
    app = make_app(hub, hello_fields, access, refusals)
    runner = web.AppRunner(app, handle_signals=False, access_log=None)  # no access log: URLs may hold the token
    await runner.setup()
    await web.SockSite(runner, sock).start()
    no_token = "" if config.token else "no token: --no-token, loopback only; "
    announce(f"serving {page_url(config, port)} ({no_token}Ctrl-C stops; report -> {report_path(config.out)})")

    loop = asyncio.get_running_loop()
    stop = asyncio.Event() if stop is None else stop
    # asyncio's remove_signal_handler puts Python's defaults back, not what was there before
    # (an embedding application's handler, or SIG_IGN in a test worker): restored by hand below.
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, stop.set)
    rss_task = asyncio.create_task(rss.run())
    started = time.time()
    stats = engine.stats
    error: BaseException | None = None
    try:
        if config.wait_clients and not await _wait_for_clients(hub, config.wait_clients, stop):
            stats.stop_reason = "interrupted"
        else:
            stats.stop_reason = await _replay(config, source, engine, hub, stop)
    except Exception as exc:  # noqa: BLE001 - reported to the clients and the report, then re-raised
        error = exc
        stats.stop_reason = f"error: {exc}"
        hub.set_status(protocol.status("stopping", f"stopped by an error: {exc}"))
    finally:
        for sig in STOP_SIGNALS:
            loop.remove_signal_handler(sig)
            if previous[sig] is not None:  # None: a handler not installed from Python, left as it is
                signal.signal(sig, previous[sig])
        await drain_clients(hub, DRAIN_S if stats.stop_reason in ("recording ended", "source stopped") else 0.2)
        await close_all(app, protocol.CLOSE_GOING_AWAY, str(stats.stop_reason)[:100])
        await runner.cleanup()
        source.close()
        rss_task.cancel()
        rss.sample()
    report = build_report(config.for_report(), graphs, stats, hub, started_wall_s=started,
                          stopped_wall_s=time.time(), rss_mb=rss.summary(), refusals=refusals)
    write_json_atomic(report_path(config.out), report)
    if error is not None:
        raise error
    return report


async def _wait_for_clients(hub: ClientHub, count: int, stop: asyncio.Event) -> bool:
    hub.set_status(protocol.status("waiting", f"waiting for {count} client(s) before the replay starts"))
    while hub.seen < count:
        hub.connected.clear()
        waiters = {asyncio.create_task(hub.connected.wait()), asyncio.create_task(stop.wait())}
        await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        for task in waiters:
            task.cancel()
        if stop.is_set():
            return False
    return True


async def _replay(config: ServeConfig, source: Any, engine: ServeEngine, hub: ClientHub, stop: asyncio.Event) -> str:
    kind = "live source" if source.live else "recording"
    hub.set_status(protocol.status("running", f"{kind} {Path(config.source).name} at {config.speed:g}x"
                                   if not source.live else f"{kind} {config.source}"))
    engine_task = asyncio.create_task(engine.run())
    stop_task = asyncio.create_task(stop.wait())
    timer = asyncio.create_task(asyncio.sleep(config.duration_s)) if config.duration_s else None
    waiting = {engine_task, stop_task, *([timer] if timer else [])}
    done, _ = await asyncio.wait(waiting, return_when=asyncio.FIRST_COMPLETED)
    for task in waiting - done:
        task.cancel()
    if engine_task in done:
        reason = engine_task.result()  # raises what the engine raised
    else:
        with_cancel = [engine_task]
        await asyncio.gather(*with_cancel, return_exceptions=True)
        reason = "interrupted" if stop_task in done else "duration"
    if reason == "source stopped":
        message = getattr(source, "stop_message", None) or "the live source stopped"
        hub.set_status(protocol.status("source stopped", message))
    elif reason == "recording ended":
        hub.set_status(protocol.status("recording ended", "the recording ended; the server stops"))
    else:
        why = "Ctrl-C" if reason == "interrupted" else f"--duration-s {config.duration_s:g}"
        hub.set_status(protocol.status("stopping", f"the server stops ({why})"))
    return reason
