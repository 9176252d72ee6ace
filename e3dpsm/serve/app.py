"""The aiohttp application: the page at `/`, the socket at `/ws`, and who may reach them.

Every request first passes the Host check (security.py); the page and the socket then need
the token, by `?token=...` or by the cookie the page sets when opened with it; the socket
also needs an allowed Origin. Every response carries the security headers. The page is one
HTML document with its script and style inlined at start-up from the package's static/
folder, so the token guards everything there is, the page needs no network beyond this
server, and its Content-Security-Policy can admit exactly that script and style by hash.
"""
from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass
from importlib import resources
from typing import Any, Awaitable, Callable

from aiohttp import WSMsgType, hdrs, web

from e3dpsm.serve import protocol
from e3dpsm.serve.clients import ClientChannel, ClientHub
from e3dpsm.serve.protocol import ProtocolError
from e3dpsm.serve.security import Access, Refusals, TokenBucket, csp_hash, response_headers

log = logging.getLogger(__name__)

CLOSE_TIMEOUT_S = 2.0  # how long a closing client may take to answer the close frame
SOCKETS_KEY = web.AppKey("sockets", dict)


@dataclass(frozen=True)
class Page:
    html: str
    csp_hashes: tuple[str, str]  # of the inlined script, of the inlined style


def load_page() -> Page:
    static = resources.files("e3dpsm.serve") / "static"
    script = (static / "app.js").read_text(encoding="utf-8")
    style = (static / "style.css").read_text(encoding="utf-8")
    html = (static / "index.html").read_text(encoding="utf-8")
    return Page(html.replace("/*STYLE*/", style).replace("/*SCRIPT*/", script), (csp_hash(script), csp_hash(style)))


def _refusal(status: int, text: str) -> web.Response:
    return web.Response(status=status, text=f"{status}: {text}\n")


def _token_refusal(verdict: int, refusals: Refusals) -> web.Response:
    if verdict == 401:
        refusals.token_missing += 1
        return _refusal(401, "this server needs its token: open the URL `e3dpsm serve` printed (it ends in "
                             "?token=...); the page then keeps it in a cookie")
    refusals.token_wrong += 1
    return _refusal(403, "wrong token (a cookie from an earlier server on this port? open the URL this one printed)")


def _guards(access: Access, refusals: Refusals) -> tuple[Any, Callable[..., Awaitable[None]]]:
    """The Host check before every handler, and the security headers on every response."""

    @web.middleware
    async def host_guard(request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]):
        if access.request_host(request.headers.get(hdrs.HOST)) is None:
            refusals.host += 1
            return _refusal(403, "this server answers only to a loopback name or the --host it was bound to, "
                                 "with its port, in the Host header (a guard against DNS rebinding)")
        return await handler(request)

    async def security_headers(request: web.Request, response: web.StreamResponse) -> None:
        for name, value in response_headers(None, None).items():  # the page set its own CSP already
            response.headers.setdefault(name, value)

    return host_guard, security_headers


def _socket_refusal(request: web.Request, access: Access, refusals: Refusals) -> web.Response | None:
    origin = request.headers.get(hdrs.ORIGIN)
    if origin is None and access.token is None:
        refusals.origin += 1
        return _refusal(403, "a client without an Origin header needs the token, and this server runs with "
                             "--no-token: only its own pages may connect")
    if origin is not None and not access.origin_allowed(origin):
        refusals.origin += 1
        return _refusal(403, "a WebSocket from a foreign origin: only this server's own page and --allow-origin "
                             "origins may connect")
    verdict = access.token_verdict(request.query.get("token"), request.cookies.get(access.cookie_name))
    return None if verdict == 200 else _token_refusal(verdict, refusals)


def make_app(hub: ClientHub, hello_fields: dict[str, Any], access: Access, refusals: Refusals) -> web.Application:
    host_guard, security_headers = _guards(access, refusals)
    app = web.Application(middlewares=[host_guard])
    app.on_response_prepare.append(security_headers)
    app[SOCKETS_KEY] = {}
    page = load_page()

    async def index(request: web.Request) -> web.StreamResponse:
        query_token = request.query.get("token")
        verdict = access.token_verdict(query_token, request.cookies.get(access.cookie_name))
        if verdict != 200:
            return _token_refusal(verdict, refusals)
        if access.token is not None and query_token is not None:
            # Trade the URL's token for a cookie and take it out of the address bar and history.
            response = web.Response(status=303, headers={hdrs.LOCATION: "/"})
            response.set_cookie(access.cookie_name, access.cookie_value, path="/", httponly=True, samesite="Strict")
            return response
        host = access.request_host(request.headers.get(hdrs.HOST))
        return web.Response(text=page.html, content_type="text/html", headers=response_headers(host, page.csp_hashes))

    async def socket(request: web.Request) -> web.StreamResponse:
        refused = _socket_refusal(request, access, refusals)
        if refused is not None:
            return refused
        ws = web.WebSocketResponse(timeout=CLOSE_TIMEOUT_S, compress=False,
                                   max_msg_size=protocol.MAX_CLIENT_MESSAGE_BYTES)
        await ws.prepare(request)
        channel = hub.add(request.remote or "?")
        channel.put_control(protocol.hello(**hello_fields, client_id=channel.client_id))
        if hub.status is not None:
            channel.put_control(hub.status)
        sender = asyncio.create_task(_send_loop(ws, channel))
        app[SOCKETS_KEY][channel.client_id] = (ws, sender, channel)
        try:
            await _receive_loop(ws, channel, refusals)
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender
            channel.closed(ws.close_code, None)
            app[SOCKETS_KEY].pop(channel.client_id, None)
            hub.retire(channel)
        return ws

    app.router.add_get("/", index)
    app.router.add_get("/ws", socket)
    return app


async def _send_loop(ws: web.WebSocketResponse, channel: ClientChannel) -> None:
    while not ws.closed:
        kind, text, pose = await channel.next_message()
        try:
            await ws.send_str(text)
        except (ConnectionError, RuntimeError):  # closing under us: the receive loop ends the client
            return
        channel.sent(kind, pose)


async def _receive_loop(ws: web.WebSocketResponse, channel: ClientChannel, refusals: Refusals) -> None:
    bucket = TokenBucket(protocol.CLIENT_MESSAGES_PER_S, protocol.CLIENT_MESSAGE_BURST)
    async for msg in ws:
        if msg.type == WSMsgType.ERROR:  # e.g. over max_msg_size: aiohttp closed it with the error's code (1009)
            channel.closed(getattr(msg.data, "code", ws.close_code), str(msg.data)[:120])
            return
        try:
            if not bucket.take():
                refusals.rate_limited += 1
                raise ProtocolError(protocol.CLOSE_POLICY, f"more than {protocol.CLIENT_MESSAGES_PER_S:g} messages "
                                    f"a second (bursts of {protocol.CLIENT_MESSAGE_BURST})")
            if msg.type == WSMsgType.BINARY:
                raise ProtocolError(protocol.CLOSE_UNSUPPORTED, "binary messages are not part of the protocol")
            if msg.type != WSMsgType.TEXT:
                continue
            kind, payload = protocol.parse_client_message(msg.data)
        except ProtocolError as exc:
            log.info("client %d closed: %s (%d)", channel.client_id, exc.reason, exc.code)
            channel.closed(exc.code, exc.reason)
            await ws.close(code=exc.code, message=exc.reason.encode("utf-8"))
            return
        if kind == "ping":
            channel.put_control(protocol.pong(payload, time.time() * 1e3))
        elif kind == "latency":
            channel.page_reported(payload)
        elif kind == "hello":
            channel.agent = payload


async def drain_clients(hub: ClientHub, timeout_s: float) -> None:
    """Give open clients up to `timeout_s` to receive what is queued (the end of a recording)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while loop.time() < deadline and any(c.backlog or c.has_control for c in hub.open_clients()):
        await asyncio.sleep(0.02)


async def close_all(app: web.Application, code: int, reason: str) -> None:
    """Close every open socket with `code`; a client that does not answer is cut off."""
    async def close_one(ws: web.WebSocketResponse, sender: asyncio.Task, channel: ClientChannel) -> None:
        sender.cancel()
        channel.closed(code, reason)
        try:
            await asyncio.wait_for(ws.close(code=code, message=reason.encode("utf-8"), drain=False),
                                   CLOSE_TIMEOUT_S + 0.5)
        except (asyncio.TimeoutError, ConnectionError, RuntimeError):
            pass

    sockets = list(app[SOCKETS_KEY].values())
    await asyncio.gather(*(close_one(*socket) for socket in sockets), return_exceptions=True)
