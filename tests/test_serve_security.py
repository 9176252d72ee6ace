"""`e3dpsm serve`'s web security, one rule per test (docs/serve.md#security): the token (401
without, 403 wrong, traded for a cookie the socket accepts), the Host check against DNS
rebinding, the Origin check against cross-site WebSocket hijacking, the headers (CSP by hash,
no framing), bounded client messages (size and rate), --no-token on loopback only, and a report
without the token. The rules' pieces are checked alone first, then on a running server."""
from __future__ import annotations

import asyncio
import base64
import hashlib
import hmac
import json
import re
import socket

import aiohttp
import pytest

from _runtime_helpers import exported_tiny
from _serve_helpers import ServerProcess, write_recording
from e3dpsm.cli import main
from e3dpsm.serve import protocol
from e3dpsm.serve.security import (Access, TokenBucket, csp_hash, is_loopback, netloc, new_token, normalise_origin,
                                   parse_host_header, response_headers)

ALLOWED = "http://viewer.example:9000"  # the shared server's --allow-origin


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    return exported_tiny(str(tmp_path_factory.getbasetemp()))[1]


@pytest.fixture(scope="module")
def server(graph, tmp_path_factory):
    """One looping server with a chosen token and one --allow-origin, probed by the rule tests."""
    folder = tmp_path_factory.mktemp("serve_security")
    recording = write_recording(folder / "seq", 30)
    with ServerProcess(["--model", str(graph), "--source", str(recording), "--loop", "--threads", "1",
                        "--token", "chosen-secret", "--allow-origin", ALLOWED, "--out", str(folder / "report")]) as s:
        yield s


def http_get(url: str, headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], str]:
    async def go():
        async with aiohttp.ClientSession() as session:
            async with session.get(url, headers=headers or {}, allow_redirects=False) as response:
                return response.status, dict(response.headers), await response.text()

    return asyncio.run(go())


def ws_open(url: str, headers: dict[str, str] | None = None) -> str | int:
    """"hello" when the socket opens (its first message), else the handshake's HTTP status."""
    async def go():
        async with aiohttp.ClientSession() as session:
            try:
                async with session.ws_connect(url, headers=headers or {}) as ws:
                    return json.loads((await ws.receive(timeout=20)).data)["type"]
            except aiohttp.WSServerHandshakeError as exc:
                return exc.status

    return asyncio.run(go())


def cookie_header(server: ServerProcess) -> dict[str, str]:
    """The cookie the page sets when opened with the printed URL, as a browser sends it back."""
    status, headers, _ = http_get(server.url)
    assert status == 303
    name, value = headers["Set-Cookie"].split(";")[0].split("=", 1)
    return {"Cookie": f"{name}={value}"}


# ---- the pieces, alone -----------------------------------------------------------------------------------
def test_host_headers_and_origins_are_read_as_browsers_write_them():
    assert parse_host_header("127.0.0.1:8765") == "127.0.0.1:8765"
    assert parse_host_header("LocalHost:8765") == "localhost:8765"
    assert parse_host_header("[0:0:0:0:0:0:0:1]:8765") == "[::1]:8765"
    assert parse_host_header("localhost") == "localhost:80"  # no port: the scheme's default
    for bad in ("", "[::1", "a:b:c", "host:http", "host:123456"):
        assert parse_host_header(bad) is None
    assert normalise_origin("HTTPS://Viewer.Example.org") == "https://viewer.example.org:443"
    assert normalise_origin("http://[::1]:9") == "http://[::1]:9"
    for bad in ("null", "*", "http://x/page", "ftp://x", "http://u@x", "http://x:99999", "http://*.x"):
        with pytest.raises(ValueError):
            normalise_origin(bad)


def test_the_rules_of_one_server():
    access = Access.for_server("127.0.0.1", 8765, "secret", ("https://viewer.example.org",))
    assert access.request_host("localhost:8765") == "localhost:8765"
    assert access.request_host("[::1]:8765") == "[::1]:8765"
    assert access.request_host("localhost:8766") is None  # another port: another server
    assert access.request_host("rebound.example:8765") is None and access.request_host(None) is None
    assert access.origin_allowed("http://127.0.0.1:8765") and access.origin_allowed("http://localhost:8765")
    assert access.origin_allowed("https://viewer.example.org")
    assert access.origin_allowed("https://viewer.example.org:443")
    for foreign in ("https://127.0.0.1:8765", "http://127.0.0.1:8766", "http://evil.example:8765", "null",
                    "https://viewer.example.org:8443"):
        assert not access.origin_allowed(foreign), foreign
    assert access.token_verdict(None, None) == 401
    assert access.token_verdict("secret", None) == access.token_verdict(None, access.cookie_value) == 200
    assert access.token_verdict("wrong", access.cookie_value) == 403  # a wrong URL is not hidden by a cookie
    assert access.token_verdict(None, "secret") == 403  # the cookie is derived from the token, not the token
    assert access.cookie_name.endswith("8765") and "secret" not in access.cookie_value
    bound = Access.for_server("192.0.2.7", 8765, "secret")
    assert bound.request_host("192.0.2.7:8765") and bound.request_host("127.0.0.1:8765")


def test_the_token_bucket_admits_its_burst_then_its_rate():
    now = [0.0]
    bucket = TokenBucket(rate=10.0, burst=4, clock=lambda: now[0])
    assert [bucket.take() for _ in range(5)] == [True] * 4 + [False]
    now[0] = 0.25  # 2.5 tokens back: two messages, not three
    assert [bucket.take() for _ in range(3)] == [True, True, False]
    now[0] = 100.0  # refilled to the burst, never beyond
    assert sum(bucket.take() for _ in range(10)) == 4


def test_no_token_off_loopback_is_refused_with_one_line(capsys):
    for host in ("0.0.0.0", "192.0.2.7", "::", "viewer.example.org"):
        assert main(["serve", "--model", "none.onnx", "--source", "none.h5", "--host", host, "--no-token"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("e3dpsm serve: error: --no-token") and host in err[0]
    # the rules' own guard, for callers that build them without the CLI
    from e3dpsm.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^--no-token is allowed on loopback only, not with --host 0\.0\.0\.0$"):
        Access.for_server("0.0.0.0", 8765, None)



def test_csp_hash_matches_the_csp_specifications_example():
    # CSP Level 2, "hash-source" (https://www.w3.org/TR/CSP2/#script-src-hash-usage): alert('Hello, world.');
    assert csp_hash("alert('Hello, world.');") == "'sha256-qznLcsROx4GACP2dm0UCKCzCG+HiZ1guq6ZZDob/Tng='"


def test_the_page_headers_admit_its_own_script_style_and_socket_only():
    headers = response_headers("127.0.0.1:8765", ("'sha256-AAA='", "'sha256-BBB='"))
    directives = dict(part.strip().split(" ", 1) for part in headers["Content-Security-Policy"].split(";"))
    assert directives == {"default-src": "'none'", "script-src": "'sha256-AAA='", "style-src": "'sha256-BBB='",
                          "connect-src": "'self' ws://127.0.0.1:8765", "base-uri": "'none'", "form-action": "'none'",
                          "frame-ancestors": "'none'"}
    assert {k: v for k, v in headers.items() if k != "Content-Security-Policy"} == {
        "X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
        "Cache-Control": "no-store"}
    for host, hashes in ((None, ("'sha256-AAA='", "'sha256-BBB='")), ("127.0.0.1:8765", None)):
        other = response_headers(host, hashes)["Content-Security-Policy"]  # an error page, or no Host: runs nothing
        assert other == "default-src 'none'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"


@pytest.mark.parametrize("host, loopback", [("localhost", True), ("LOCALHOST", True), ("127.0.0.1", True),
                                            ("127.8.9.10", True), ("::1", True), ("[::1]", True),
                                            ("0.0.0.0", False), ("192.0.2.7", False), ("localhost.example", False),
                                            ("", False), ("X127.0.0.1", False), ("127.0.0.1X", False)])
def test_loopback_is_the_127_net_ipv6_one_and_localhost(host, loopback):
    """RFC 1122 3.2.1.3 (127.0.0.0/8), RFC 4291 2.5.3 (::1), RFC 6761 6.3 (localhost)."""
    assert is_loopback(host) is loopback


def test_a_server_on_every_interface_answers_to_this_machines_names():
    access = Access.for_server("0.0.0.0", 8765, "secret")
    assert access.request_host(f"{socket.gethostname()}:8765") == netloc(socket.gethostname(), 8765)
    assert access.request_host("127.0.0.1:8765") and access.request_host("localhost:8765")
    assert access.request_host("rebound.example:8765") is None
    assert access.origin_allowed("http://localhost:8765") and not access.origin_allowed("http://rebound.example:8765")
    loopback = Access.for_server("127.0.0.1", 8765, None)  # --no-token on loopback: allowed, and admits anyone
    assert loopback.token_verdict(None, None) == 200 and loopback.token_verdict("x", "y") == 200
    if socket.gethostname().lower() != "localhost":  # bound to loopback: the machine's name is foreign
        assert loopback.request_host(f"{socket.gethostname()}:8765") is None


def test_netloc_and_host_headers_are_canonical():
    assert netloc("::1", 80) == "[::1]:80" and netloc("[0:0::1]", 9) == "[::1]:9" and netloc("Host", 1) == "host:1"
    assert parse_host_header("[::1]") == "[::1]:80" and parse_host_header("[::1]x") is None
    assert parse_host_header(" localhost:8765 ") == "localhost:8765" and parse_host_header(":8765") is None
    assert parse_host_header("localhost:12345") == "localhost:12345"  # ports have up to five digits
    assert parse_host_header("localhost:", default_port=8765) == "localhost:8765"
    assert normalise_origin("http://localhost") == "http://localhost:80"
    assert normalise_origin(" http://localhost:8765/ ") == "http://localhost:8765"
    for bad in ("http://x?q=1", "http://x#f", "http://:pw@x", "http://"):
        with pytest.raises(ValueError, match="origin"):
            normalise_origin(bad)


def test_a_name_with_one_bracket_is_not_unbracketed():
    """Only a whole `[...]` is an IPv6 literal's brackets: `[::1` is a malformed name, kept (and
    never equal to the loopback `::1` a Host check compares it with)."""
    assert netloc("[::1", 80) == "[[::1]:80" and netloc("::1]", 80) == "[::1]]:80"
    assert parse_host_header("[::1") is None


def test_a_sessions_rules_cannot_change_and_admit_no_extra_origin_by_default():
    import dataclasses

    access = Access(8765, "secret", frozenset({"127.0.0.1:8765"}))
    assert access.origin_allowed("http://127.0.0.1:8765") and not access.origin_allowed("http://viewer.example:9000")
    with pytest.raises(dataclasses.FrozenInstanceError):
        access.token = None  # type: ignore[misc]


def test_the_cookie_is_hmac_sha256_of_the_token():
    """RFC 2104 HMAC, keyed by the token, over a fixed label: checked with the hmac module's
    digest of the same label (the cookie proves the token without being it)."""
    access = Access.for_server("127.0.0.1", 8765, "secret")
    assert access.cookie_value == hmac.new(b"secret", b"e3dpsm serve cookie", "sha256").hexdigest()
    assert access.cookie_name == "e3dpsm-serve-8765"
    assert len(new_token()) == 43 and new_token() != new_token()  # 32 bytes in URL-safe base64, unpadded


def test_the_bucket_refills_at_its_rate_between_takes():
    now = [0.0]
    bucket = TokenBucket(rate=2.0, burst=1, clock=lambda: now[0])
    assert bucket.take() and not bucket.take()
    now[0] = 0.25  # half a token: not yet
    assert not bucket.take()
    now[0] = 0.5  # a whole token since the take at 0.0 (the refused one at 0.25 loses no time)
    assert bucket.take() and not bucket.take()


@pytest.mark.parametrize("bind", ["0.0.0.0", "::", ""])
def test_every_wildcard_bind_answers_to_each_interface_address_without_its_zone(monkeypatch, bind):
    """docs/serve.md: bound to every interface (0.0.0.0, ::, or the empty host, which binds all
    of them too), the machine's own addresses count as bound. An IPv6 address's zone
    (`%eth0`) is not part of a Host header (RFC 6874 leaves it out of URIs a browser sends);
    an interface's link-layer (MAC) address is no host name."""
    import psutil

    from types import SimpleNamespace as Addr

    monkeypatch.setattr(psutil, "net_if_addrs", lambda: {"eth0": [
        Addr(family=socket.AF_INET, address="192.0.2.7"), Addr(family=socket.AF_INET6, address="fe80::1%eth0"),
        Addr(family=psutil.AF_LINK, address="00:11:22:33:44:55")]})
    access = Access.for_server(bind, 8765, "secret")
    assert access.request_host("192.0.2.7:8765") == "192.0.2.7:8765"
    assert access.request_host("[fe80::1]:8765") == "[fe80::1]:8765"
    assert not any("00:11:22:33:44:55" in host for host in access.hosts)
    assert Access.for_server("127.0.0.1", 8765, "secret").request_host("192.0.2.7:8765") is None  # not bound there


@pytest.mark.parametrize("origin, why", [("ftp://x", "is not an origin like http://host:port"),
                                         ("http://u@x", "is not an origin like http://host:port"),
                                         ("http://x/page", "is not an origin: no path, query or wildcard"),
                                         ("http://x:99999", "has a bad port")])
def test_a_bad_allow_origin_says_what_is_wrong_with_it(origin, why):
    """`--allow-origin` is refused with the origin quoted and the reason (cli/serve.py shows it)."""
    with pytest.raises(ValueError) as refused:
        normalise_origin(origin)
    assert str(refused.value) == f"{origin!r} {why}"


def test_the_report_counts_no_refusal_before_the_first():
    """A new session's `refused` (docs/serve.md's report table: host, origin, token_missing,
    token_wrong, rate_limited) is all zeros, as the report writes it (dataclasses.asdict)."""
    import dataclasses

    from e3dpsm.serve.security import Refusals

    assert dataclasses.asdict(Refusals()) == {"host": 0, "origin": 0, "token_missing": 0, "token_wrong": 0,
                                              "rate_limited": 0}


# ---- the rules on a running server, each alone -----------------------------------------------------------
def test_the_page_without_a_token_is_401(server):
    status, _, text = http_get(f"{server.base}/")
    assert status == 401 and "pose-count" not in text and "token" in text


def test_a_wrong_token_is_403_on_the_page_and_the_socket(server):
    assert http_get(f"{server.base}/?token=wrong")[0] == 403
    assert ws_open(f"{server.base}/ws?token=wrong") == 403
    name = cookie_header(server)["Cookie"].split("=")[0]
    assert http_get(f"{server.base}/", {"Cookie": f"{name}=stale"})[0] == 403
    assert ws_open(f"{server.base}/ws") == 401


def test_the_page_trades_the_token_for_a_cookie_the_socket_accepts(server):
    status, headers, text = http_get(server.url)
    assert status == 303 and headers["Location"] == "/" and "pose-count" not in text
    cookie = headers["Set-Cookie"]
    attributes = {part.strip().split("=")[0].lower(): part.strip() for part in cookie.split(";")[1:]}
    assert cookie.startswith(f"e3dpsm-serve-{server.port}=")  # one name per port: servers do not clobber
    assert "httponly" in attributes and attributes["samesite"].lower() == "samesite=strict"
    assert attributes["path"] == "Path=/" and "chosen-secret" not in cookie
    sent = cookie_header(server)
    status, _, text = http_get(f"{server.base}/", sent)
    assert status == 200 and "pose-count" in text
    assert ws_open(f"{server.base}/ws", sent) == "hello"  # the socket with the cookie alone
    other_port = sent["Cookie"].replace(f"e3dpsm-serve-{server.port}=", f"e3dpsm-serve-{server.port + 1}=")
    assert ws_open(f"{server.base}/ws", {"Cookie": other_port}) == 401


def test_the_socket_refuses_a_foreign_origin(server):
    for origin in ("http://evil.example", f"http://evil.example:{server.port}", f"http://127.0.0.1:{server.port + 1}",
                   f"https://127.0.0.1:{server.port}", "null"):
        assert ws_open(server.ws, {"Origin": origin}) == 403, origin  # even with the token


def test_the_socket_accepts_the_pages_own_origins(server):
    cookie = cookie_header(server)
    for name in ("127.0.0.1", "localhost", "[::1]"):
        assert ws_open(f"{server.base}/ws", {**cookie, "Origin": f"http://{name}:{server.port}"}) == "hello", name


def test_allow_origin_admits_that_origin_and_no_other(server):
    cookie = cookie_header(server)
    assert ws_open(f"{server.base}/ws", {**cookie, "Origin": ALLOWED}) == "hello"
    assert ws_open(f"{server.base}/ws", {**cookie, "Origin": ALLOWED.replace("9000", "9001")}) == 403


def test_a_foreign_host_is_refused_on_the_page_and_the_socket(server):
    rebound = {"Host": f"rebound.example:{server.port}"}  # a DNS-rebinding page's requests
    assert http_get(server.url, rebound)[0] == 403
    assert ws_open(server.ws, rebound) == 403
    assert http_get(server.url, {"Host": f"127.0.0.1:{server.port + 1}"})[0] == 403
    assert http_get(server.url, {"Host": f"localhost:{server.port}"})[0] == 303


def _inline(html: str, tag: str) -> str:
    return re.search(rf"<{tag}>(.*)</{tag}>", html, re.S).group(1)


def test_every_response_carries_the_security_headers(server):
    cookie = cookie_header(server)
    fixed = {"X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
             "Cache-Control": "no-store"}
    responses = {"page": http_get(f"{server.base}/", cookie), "401": http_get(f"{server.base}/"),
                 "303": http_get(server.url), "404": http_get(f"{server.base}/missing", cookie),
                 "foreign host": http_get(server.url, {"Host": "rebound.example"})}
    assert [r[0] for r in responses.values()] == [200, 401, 303, 404, 403]
    for name, (_, headers, _) in responses.items():
        assert {k: headers.get(k) for k in fixed} == fixed, name
        assert "frame-ancestors 'none'" in headers["Content-Security-Policy"], name
        assert headers["Content-Security-Policy"].startswith("default-src 'none'"), name
    _, headers, html = responses["page"]
    policy = dict(part.strip().split(" ", 1) for part in headers["Content-Security-Policy"].split(";"))
    digest = lambda text: "'sha256-" + base64.b64encode(hashlib.sha256(text.encode()).digest()).decode() + "'"
    assert policy["script-src"] == digest(_inline(html, "script"))  # the page's own script and nothing else
    assert policy["style-src"] == digest(_inline(html, "style"))
    assert policy["connect-src"] == f"'self' ws://127.0.0.1:{server.port}"
    assert "script-src" not in responses["401"][1]["Content-Security-Policy"]  # anything else runs nothing


# ---- servers of their own ------------------------------------------------------------------------------
async def _flood_and_watch(server: ServerProcess) -> tuple[list[int], int | None, int | None]:
    """A good client reads poses while one client floods pings and another sends 70 KiB; each
    reads until the server closes it: (the good one's pose seqs, the two others' close codes)."""
    async def client(session: aiohttp.ClientSession, send: list[str]) -> tuple[list[int], int | None]:
        async with session.ws_connect(server.ws) as ws:
            for text in send:
                await ws.send_str(text)
            seqs = [m["seq"] async for m in _texts(ws) if m["type"] == "pose"]
            return seqs, ws.close_code

    async with aiohttp.ClientSession() as session:
        (seqs, _), (_, flood_code), (_, oversize_code) = await asyncio.gather(
            client(session, []), client(session, ['{"type": "ping"}'] * (protocol.CLIENT_MESSAGE_BURST * 3)),
            client(session, ['{"type": "hello", "agent": "' + "x" * 70_000 + '"}']))
    return seqs, flood_code, oversize_code


async def _texts(ws):
    async for msg in ws:
        if msg.type != aiohttp.WSMsgType.TEXT:
            return
        yield json.loads(msg.data)


def test_a_flooding_or_oversized_client_is_closed_while_others_keep_receiving(graph, tmp_path):
    recording = write_recording(tmp_path / "seq", 100, seed=7)
    out = tmp_path / "report"
    with ServerProcess(["--model", str(graph), "--source", str(recording), "--wait-clients", "3", "--threads", "1",
                        "--out", str(out)]) as server:
        seqs, flood_code, oversize_code = asyncio.run(_flood_and_watch(server))
        rc, _, stderr = server.wait()
    assert rc == 0, stderr
    assert flood_code == protocol.CLOSE_POLICY and oversize_code == protocol.CLOSE_TOO_BIG
    report = json.loads((out / "serve.report.json").read_text())
    assert seqs == list(range(report["poses"])) and report["poses"] >= 95  # every pose, in order
    by_id = {c["client_id"]: c for c in report["clients"]}
    assert by_id[1]["close_code"] == protocol.CLOSE_POLICY and "a second" in by_id[1]["close_reason"]
    assert by_id[2]["close_code"] == protocol.CLOSE_TOO_BIG
    assert report["refused"]["rate_limited"] == 1


def test_no_token_serves_its_own_pages_only(graph, tmp_path):
    recording = write_recording(tmp_path / "seq", 30)
    with ServerProcess(["--model", str(graph), "--source", str(recording), "--loop", "--threads", "1", "--no-token",
                        "--out", str(tmp_path / "report")]) as server:
        assert server.token is None and "(no token: --no-token, loopback only; " in server.line
        status, _, text = http_get(server.url)
        assert status == 200 and "pose-count" in text
        own = {"Origin": f"http://127.0.0.1:{server.port}"}
        assert ws_open(server.ws, own) == "hello"
        assert ws_open(server.ws) == 403  # no Origin and no token: not a page of this server
        assert ws_open(server.ws, {"Origin": "http://evil.example"}) == 403
        assert http_get(server.url, {"Host": f"rebound.example:{server.port}"})[0] == 403


async def _poses(url: str, count: int) -> list[tuple[int, int]]:
    async with aiohttp.ClientSession() as session:
        async with session.ws_connect(url) as ws:
            seqs = []
            async for msg in ws:
                m = json.loads(msg.data)
                if m["type"] == "pose":
                    seqs.append((m["seq"], m["t_us"]))
                if len(seqs) >= count:
                    return seqs
    return seqs


def test_a_generated_token_guards_everything_and_stays_out_of_the_report(graph, tmp_path):
    recording = write_recording(tmp_path / "seq", 30)
    out = tmp_path / "report"
    with ServerProcess(["--model", str(graph), "--source", str(recording), "--loop", "--threads", "1",
                        "--out", str(out)]) as server:
        token = server.token
        assert token and len(token) >= 43 and server.url == f"http://127.0.0.1:{server.port}/?token={token}"
        cookie = cookie_header(server)
        probes = [http_get(f"{server.base}/")[0], ws_open(f"{server.base}/ws"), http_get(f"{server.base}/?token=x")[0],
                  ws_open(f"{server.base}/ws?token=x"), http_get(server.url, {"Host": "rebound.example"})[0],
                  ws_open(server.ws, {"Origin": "http://evil.example"}), ws_open(server.ws)]
        seqs = asyncio.run(_poses(server.ws, 45))  # past the 29 poses of one pass: the loop restarted
        server.interrupt()
        rc, _, stderr = server.wait(timeout_s=30)
    assert probes == [401, 401, 403, 403, 403, 403, "hello"]
    assert all(b[0] == a[0] + 1 and b[1] > a[1] for a, b in zip(seqs, seqs[1:]))  # in order across the loop
    assert rc == 0, stderr
    text = (out / "serve.report.json").read_text()
    report = json.loads(text)
    assert token not in text and cookie["Cookie"].split("=", 1)[1] not in text and report["config"]["token"] == "(set)"
    assert report["refused"] == {"host": 1, "origin": 1, "token_missing": 2, "token_wrong": 2, "rate_limited": 0}
    assert report["stop_reason"] == "interrupted" and report["passes"] >= 2 and report["poses"] >= 45
    assert not [p for p in out.iterdir() if p.name != "serve.report.json"]  # no temporary left behind
