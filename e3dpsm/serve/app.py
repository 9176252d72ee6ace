"""The aiohttp application: the page at `/`, the socket at `/ws`, the token check.

With a token, both need `?token=...`: missing gives 401, wrong gives 403 (compared in constant
time). The page is one HTML document with its script and style inlined at start-up from the
package's static/ folder, so a token protects everything there is and the page needs no
network beyond this server.
"""
from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import time
from importlib import resources
from typing import Any

from aiohttp import WSMsgType, web

from e3dpsm.serve import protocol
from e3dpsm.serve.clients import ClientChannel, ClientHub
from e3dpsm.serve.protocol import ProtocolError

log = logging.getLogger(__name__)

CLOSE_TIMEOUT_S = 2.0  # how long a closing client may take to answer the close frame
HUB_KEY = web.AppKey("hub", ClientHub)
SOCKETS_KEY = web.AppKey("sockets", dict)


def page_html() -> str:
    static = resources.files("e3dpsm.serve") / "static"
    html = (static / "index.html").read_text(encoding="utf-8")
    return (html.replace("/*STYLE*/", (static / "style.css").read_text(encoding="utf-8"))
                .replace("/*SCRIPT*/", (static / "app.js").read_text(encoding="utf-8")))


def _token_refusal(request: web.Request, token: str | None) -> web.Response | None:
    if token is None:
        return None
    given = request.query.get("token")
    if given is None:
        return web.Response(status=401, text="401: this server needs ?token=... (the --token it was started with)\n")
    if not hmac.compare_digest(given.encode("utf-8"), token.encode("utf-8")):
        return web.Response(status=403, text="403: wrong token\n")
    return None


def make_app(hub: ClientHub, hello_fields: dict[str, Any], token: str | None) -> web.Application:
    app = web.Application()
    app[HUB_KEY] = hub
    app[SOCKETS_KEY] = {}
    html = page_html()

    async def index(request: web.Request) -> web.StreamResponse:
        refused = _token_refusal(request, token)
        if refused is not None:
            return refused
        return web.Response(text=html, content_type="text/html", headers={"Cache-Control": "no-store"})

    async def socket(request: web.Request) -> web.StreamResponse:
        refused = _token_refusal(request, token)
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
        app[SOCKETS_KEY][channel.client_id] = (ws, sender)
        try:
            await _receive_loop(ws, channel)
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender
            channel.closed(ws.close_code, None)
            app[SOCKETS_KEY].pop(channel.client_id, None)
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


async def _receive_loop(ws: web.WebSocketResponse, channel: ClientChannel) -> None:
    async for msg in ws:
        try:
            if msg.type == WSMsgType.BINARY:
                raise ProtocolError(protocol.CLOSE_UNSUPPORTED, "binary messages are not part of the protocol")
            if msg.type == WSMsgType.ERROR:  # e.g. over max_msg_size: aiohttp closed it (1009)
                channel.closed(ws.close_code, str(ws.exception())[:120])
                return
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
    async def close_one(ws: web.WebSocketResponse, sender: asyncio.Task, client_id: int) -> None:
        sender.cancel()
        hub = app[HUB_KEY]
        hub.clients[client_id].closed(code, reason)
        try:
            await asyncio.wait_for(ws.close(code=code, message=reason.encode("utf-8"), drain=False),
                                   CLOSE_TIMEOUT_S + 0.5)
        except (asyncio.TimeoutError, ConnectionError, RuntimeError):
            pass

    sockets = list(app[SOCKETS_KEY].items())
    await asyncio.gather(*(close_one(ws, sender, cid) for cid, (ws, sender) in sockets), return_exceptions=True)
