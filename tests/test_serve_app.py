"""The viewer's aiohttp application (e3dpsm/serve/app.py) in this process, without a model: each
refusal's status, text and counter, whole; the token traded for a cookie and its attributes; the
socket's messages in and out; a misbehaving client closed with its code and reason; draining
and closing every client. tests/test_serve_security.py checks the same rules on a real server."""
from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import socket
import time

import aiohttp
import pytest
from aiohttp.test_utils import TestServer

from e3dpsm.serve import protocol
from e3dpsm.serve.app import close_all, drain_clients, load_page, make_app
from e3dpsm.serve.clients import ClientHub
from e3dpsm.serve.protocol import PoseMessage
from e3dpsm.serve.security import Access, Refusals, csp_hash, response_headers

TOKEN = "app-test-token"
HELLO = dict(joints=["head", "neck"], bones=[(0, 1)], models=["tiny"], window_ms=20.0, sensor_hw=(12, 16),
             frame_hw=(6, 8), source="test", live=False, ground_truth=False, speed=1.0)
HOST_REFUSAL = ("403: this server answers only to a loopback name or the --host it was bound to, with its port, "
                "in the Host header (a guard against DNS rebinding)\n")
MISSING = ("401: this server needs its token: open the URL `e3dpsm serve` printed (it ends in ?token=...); "
           "the page then keeps it in a cookie\n")
WRONG = "403: wrong token (a cookie from an earlier server on this port? open the URL this one printed)\n"
FOREIGN = ("403: a WebSocket from a foreign origin: only this server's own page and --allow-origin origins may "
           "connect\n")
NO_ORIGIN = ("403: a client without an Origin header needs the token, and this server runs with --no-token: "
             "only its own pages may connect\n")


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Served:
    """make_app on a real loopback port; `run(scenario)` calls scenario(self, session)."""

    def __init__(self, token: str | None = TOKEN, backlog: int = 8) -> None:
        self.port = _free_port()
        self.access = Access.for_server("127.0.0.1", self.port, token)
        self.refusals = Refusals()
        self.hub = ClientHub(backlog)
        self.app = make_app(self.hub, HELLO, self.access, self.refusals)
        self.base = f"http://127.0.0.1:{self.port}"
        self.origin = f"http://127.0.0.1:{self.port}"

    def run(self, scenario):
        async def go():
            server = TestServer(self.app, host="127.0.0.1", port=self.port)
            await server.start_server()
            try:
                async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as session:  # keeps cookies of IP hosts
                    return await scenario(self, session)
            finally:
                await server.close()
        return asyncio.run(go())

    @property
    def token_query(self) -> str:
        return f"?token={TOKEN}"


async def _get(session, url, **headers):
    async with session.get(url, headers=headers, allow_redirects=False) as response:
        return response.status, response.headers, await response.text()


def test_a_foreign_host_is_refused_and_counted() -> None:
    served = Served()

    async def scenario(s, session):
        return [await _get(session, s.base + "/" + s.token_query, Host="evil.example:80"),
                await _get(session, s.base + "/ws" + s.token_query, Host=f"attacker.test:{s.port}"),
                await _get(session, s.base + "/" + s.token_query)]  # its own Host: passes the guard
    (page, _, page_text), (ws, _, ws_text), (own, _, _) = served.run(scenario)
    assert (page, page_text) == (403, HOST_REFUSAL) and (ws, ws_text) == (403, HOST_REFUSAL)
    assert own == 303 and served.refusals.host == 2


def test_the_page_needs_the_token() -> None:
    served = Served()

    async def scenario(s, session):
        return [await _get(session, s.base + "/"), await _get(session, s.base + "/?token=wrong"),
                await _get(session, s.base + "/", Cookie=f"{s.access.cookie_name}=stale")]
    (missing, _, missing_text), (wrong, _, wrong_text), (stale, _, stale_text) = served.run(scenario)
    assert (missing, missing_text) == (401, MISSING)
    assert (wrong, wrong_text) == (403, WRONG) and (stale, stale_text) == (403, WRONG)
    assert (served.refusals.token_missing, served.refusals.token_wrong) == (1, 2)


def test_the_token_is_traded_for_a_cookie_and_the_page_served_with_it() -> None:
    served = Served()

    async def scenario(s, session):
        async with session.get(s.base + "/" + s.token_query, allow_redirects=False) as traded:
            cookie = traded.cookies[s.access.cookie_name]
            first = (traded.status, traded.headers["Location"], cookie.value, dict(cookie))
        page = await _get(session, s.base + "/")  # the session sends the cookie back
        return first, page
    (status, location, value, attributes), (page_status, headers, html) = served.run(scenario)
    assert (status, location, value) == (303, "/", served.access.cookie_value)
    assert attributes["path"] == "/" and attributes["httponly"] is True and attributes["samesite"] == "Strict"
    page = load_page()
    assert page_status == 200 and html == page.html and headers["Content-Type"].startswith("text/html")
    host = f"127.0.0.1:{served.port}"
    for name, value in response_headers(host, page.csp_hashes).items():
        assert headers[name] == value
    assert served.refusals == Refusals()


def test_every_other_response_carries_the_default_headers() -> None:
    served = Served()

    async def scenario(s, session):
        return [await _get(session, s.base + "/"), await _get(session, s.base + "/nothing-here")]
    (status, headers, _), (missing, missing_headers, _) = served.run(scenario)
    assert (status, missing) == (401, 404)
    for got in (headers, missing_headers):
        for name, value in response_headers(None, None).items():
            assert got[name] == value


def test_the_socket_is_not_compressed_even_when_the_client_offers() -> None:
    """permessage-deflate stays off: poses are small and frequent, and compressed secrets beside
    attacker-chosen text leak their length (the CRIME family)."""
    served = Served()

    async def scenario(s, session):
        async with session.ws_connect(s.base + "/ws" + s.token_query, headers={"Origin": s.origin}, compress=15) as ws:
            await ws.receive(timeout=5)
            return ws.compress
    assert served.run(scenario) == 0


def test_the_page_inlines_its_script_and_style_admitted_by_hash() -> None:
    from importlib import resources

    static = resources.files("e3dpsm.serve") / "static"
    script, style = ((static / name).read_text(encoding="utf-8") for name in ("app.js", "style.css"))
    page = load_page()
    assert page.csp_hashes == (csp_hash(script), csp_hash(style))
    assert script in page.html and style in page.html
    assert "/*SCRIPT*/" not in page.html and "/*STYLE*/" not in page.html
    with pytest.raises(dataclasses.FrozenInstanceError):
        page.html = ""


async def _handshake(session, url, **headers):
    """The status and text of a WebSocket handshake the server refuses."""
    async with session.get(url, headers={"Connection": "Upgrade", "Upgrade": "websocket", "Sec-WebSocket-Version": "13",
                                         "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==", **headers}) as response:
        return response.status, await response.text()


async def _ws_status(session, url, **headers):
    try:
        async with session.ws_connect(url, headers=headers) as ws:
            return json.loads((await ws.receive(timeout=5)).data)["type"], None
    except aiohttp.WSServerHandshakeError as exc:
        return exc.status, None


def test_the_socket_refuses_foreign_origins_and_missing_tokens() -> None:
    served = Served()

    async def scenario(s, session):
        return [await _handshake(session, s.base + "/ws" + s.token_query, Origin="http://evil.example"),
                await _handshake(session, s.base + "/ws" + s.token_query, Origin="null"),
                await _handshake(session, s.base + "/ws", Origin=s.origin),
                await _handshake(session, s.base + "/ws?token=nope", Origin=s.origin),
                await _ws_status(session, s.base + "/ws" + s.token_query, Origin=s.origin),
                await _ws_status(session, s.base + "/ws" + s.token_query)]  # no Origin, with the token
    foreign, sandboxed, missing, wrong, own, tool = served.run(scenario)
    assert foreign == (403, FOREIGN) and sandboxed == (403, FOREIGN)
    assert missing == (401, MISSING) and wrong == (403, WRONG)
    assert own[0] == "hello" and tool[0] == "hello"
    r = served.refusals
    assert (r.origin, r.token_missing, r.token_wrong, r.host, r.rate_limited) == (2, 1, 1, 0, 0)


def test_without_a_token_only_the_servers_own_pages_connect() -> None:
    served = Served(token=None)

    async def scenario(s, session):
        page = await _get(session, s.base + "/")
        return (page[0], await _handshake(session, s.base + "/ws"), await _handshake(session, s.base + "/ws"),
                await _ws_status(session, s.base + "/ws", Origin=s.origin))
    page, no_origin, again, own = served.run(scenario)
    assert page == 200 and no_origin == again == (403, NO_ORIGIN) and own[0] == "hello"
    assert served.refusals.origin == 2


def test_a_socket_gets_hello_then_the_status_and_answers_pings() -> None:
    served = Served()
    served.hub.status = protocol.status("running", "stepping")

    async def scenario(s, session):
        async with session.ws_connect(s.base + "/ws" + s.token_query, headers={"Origin": s.origin}) as ws:
            hello = json.loads((await ws.receive(timeout=5)).data)
            status = (await ws.receive(timeout=5)).data
            before = time.time() * 1e3
            await ws.send_str(json.dumps({"type": "ping", "t": 12.5}))
            pong = json.loads((await ws.receive(timeout=5)).data)
            after = time.time() * 1e3
            await ws.send_str(json.dumps({"type": "hello", "agent": "pytest-agent"}))
            await ws.send_str(json.dumps({"type": "latency", "samples_ms": [4.0, 6.0], "received": 2, "drawn": 2,
                                          "gaps": 0, "out_of_order": 0}))
            channel = s.hub.open[hello["client_id"]]
            for _ in range(100):
                if channel.page_report is not None and channel.agent:
                    break
                await asyncio.sleep(0.01)
            seen = (channel.agent, channel.page_report, channel.page_latency_ms.count, s.hub.count_open())
        for _ in range(100):
            if not s.hub.open:
                break
            await asyncio.sleep(0.01)
        return hello, status, pong, (before, after), seen
    hello, status, pong, (before, after), seen = served.run(scenario)
    assert json.loads(protocol.hello(**HELLO, client_id=hello["client_id"])) == hello
    assert status == served.hub.status
    assert pong["type"] == "pong" and pong["t"] == 12.5 and before - 1 <= pong["server_wall_ms"] <= after + 1
    agent, report, samples, open_then = seen
    assert agent == "pytest-agent" and (report.received, report.drawn) == (2, 2) and samples == 2 and open_then == 1
    assert served.hub.retired == 1 and served.hub.summaries()[0]["close_code"] == 1000


@pytest.mark.parametrize("send, code, reason", [
    (lambda ws: ws.send_bytes(b"\x00"), protocol.CLOSE_UNSUPPORTED, "binary messages are not part of the protocol"),
    (lambda ws: ws.send_str("not json"), protocol.CLOSE_INVALID, "not JSON"),
    (lambda ws: ws.send_str(json.dumps({"type": "shout"})), protocol.CLOSE_POLICY,
     "unknown message type 'shout'; expected one of ping, latency, hello"),
])
def test_a_message_outside_the_protocol_closes_that_client(send, code, reason, caplog) -> None:
    served = Served()

    async def scenario(s, session):
        async with session.ws_connect(s.base + "/ws" + s.token_query, headers={"Origin": s.origin}) as ws:
            await ws.receive(timeout=5)  # hello
            await send(ws)
            closing = await ws.receive(timeout=5)
            return closing.type, closing.data, closing.extra
    with caplog.at_level(logging.INFO, logger="e3dpsm.serve.app"):
        kind, got_code, got_reason = served.run(scenario)
    assert (kind, got_code, got_reason) == (aiohttp.WSMsgType.CLOSE, code, reason)
    summary = served.hub.summaries()[0]
    assert (summary["close_code"], summary["close_reason"], summary["remote"]) == (code, reason, "127.0.0.1")
    assert [r.getMessage() for r in caplog.records if r.name == "e3dpsm.serve.app"] == [
        f"client 0 closed: {reason} ({code})"]


def test_a_flooding_client_is_closed_after_its_burst() -> None:
    served = Served()

    async def scenario(s, session):
        closes = []
        for _ in range(2):  # two floods, two clients closed
            async with session.ws_connect(s.base + "/ws" + s.token_query, headers={"Origin": s.origin}) as ws:
                await ws.receive(timeout=5)  # hello
                for _ in range(protocol.CLIENT_MESSAGE_BURST + 5):
                    await ws.send_str(json.dumps({"type": "hello", "agent": "x"}))
                while True:
                    message = await ws.receive(timeout=5)
                    if message.type == aiohttp.WSMsgType.CLOSE:
                        closes.append((message.data, message.extra))
                        break
        return closes
    closes = served.run(scenario)
    assert closes == [(protocol.CLOSE_POLICY, "more than 10 messages a second (bursts of 40)")] * 2
    assert served.refusals.rate_limited == 2


def test_an_oversized_message_closes_the_client_with_1009() -> None:
    served = Served()

    async def scenario(s, session):
        async with session.ws_connect(s.base + "/ws" + s.token_query, headers={"Origin": s.origin}) as ws:
            await ws.receive(timeout=5)
            await ws.send_str("x" * (protocol.MAX_CLIENT_MESSAGE_BYTES + 1))
            closing = await ws.receive(timeout=5)
            return closing.data
    assert served.run(scenario) == protocol.CLOSE_TOO_BIG
    assert served.hub.summaries()[0]["close_code"] == protocol.CLOSE_TOO_BIG


def test_close_all_closes_every_socket_with_the_code_and_reason() -> None:
    served = Served()

    async def scenario(s, session):
        sockets = [await session.ws_connect(s.base + "/ws" + s.token_query, headers={"Origin": s.origin})
                   for _ in range(2)]
        for ws in sockets:
            await ws.receive(timeout=5)  # hello
        await close_all(s.app, protocol.CLOSE_GOING_AWAY, "server stopping")
        closed = []
        for ws in sockets:
            message = await ws.receive(timeout=5)
            closed.append((message.type, message.data, message.extra))
            await ws.close()
        return closed
    closed = served.run(scenario)
    assert closed == [(aiohttp.WSMsgType.CLOSE, protocol.CLOSE_GOING_AWAY, "server stopping")] * 2
    assert [(s["close_code"], s["close_reason"]) for s in served.hub.summaries()] == [
        (protocol.CLOSE_GOING_AWAY, "server stopping")] * 2


def test_drain_waits_for_queued_messages_up_to_its_timeout() -> None:
    async def scenario() -> tuple[float, float, int]:
        hub = ClientHub(pose_backlog=4)
        channel = hub.add("r")
        channel.put_pose(PoseMessage(seq=0, t_us=0, window_end_wall_ms=0.0, text="p"))
        loop = asyncio.get_running_loop()
        began = loop.time()
        await drain_clients(hub, 0.3)  # nobody reads: it gives up at the timeout
        waited = loop.time() - began

        async def reader():
            await asyncio.sleep(0.1)
            await channel.next_message()
        began = loop.time()
        await asyncio.gather(drain_clients(hub, 5.0), reader())  # read after 0.1 s: done then
        return waited, loop.time() - began, channel.backlog
    waited, drained, backlog = asyncio.run(scenario())
    assert 0.3 <= waited < 1.0 and 0.1 <= drained < 1.0 and backlog == 0


def test_close_all_cuts_off_a_client_that_does_not_answer() -> None:
    """A client that never reads does not answer the close frame: close_all still returns (the
    socket's close timeout, then the wait's), and the client is recorded closed with the code."""
    served = Served()

    async def scenario(s, session):
        ws = await session.ws_connect(s.base + "/ws" + s.token_query, headers={"Origin": s.origin}, autoclose=False)
        await ws.receive(timeout=5)  # hello; nothing is read after it
        loop = asyncio.get_running_loop()
        began = loop.time()
        await asyncio.wait_for(close_all(s.app, protocol.CLOSE_GOING_AWAY, "bye"), 10.0)
        took = loop.time() - began
        await ws.close()
        return took
    assert served.run(scenario) < 10.0
    assert [(s["close_code"], s["close_reason"]) for s in served.hub.summaries()] == [(protocol.CLOSE_GOING_AWAY, "bye")]
