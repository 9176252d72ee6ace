"""Who may load the viewer and open its socket, decided in one place (no aiohttp here).

The model is Jupyter Server's: a token by default (random, printed in the URL the command
prints), exchanged on the first visit for a cookie, so that the page's socket needs no query
string. Three browser attacks are checked, each on its own:
- DNS rebinding: a site whose name re-resolves to 127.0.0.1 gets the browser to send it this
  server's answers as same-origin. Its requests carry the attacker's name in `Host`, so every
  request whose Host is not a loopback name or the bound host (with this port) is refused.
- Cross-site WebSocket hijacking: any page may open `ws://127.0.0.1:PORT/ws`; browsers send
  its `Origin`, so `/ws` admits only this server's own origins and `--allow-origin` ones. A
  missing Origin (a non-browser client) must bring the token.
- Clickjacking: the page forbids framing (headers built by `response_headers`).
"""
from __future__ import annotations

import base64
import hashlib
import hmac
import ipaddress
import secrets
import socket
import time
from dataclasses import dataclass, field
from typing import Callable
from urllib.parse import urlsplit

from e3dpsm.errors import ConfigError

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
WILDCARD_HOSTS = ("", "0.0.0.0", "::")
DEFAULT_PORTS = {"http": 80, "https": 443}
COOKIE_PREFIX = "e3dpsm-serve-"


def new_token() -> str:
    """32 random bytes, URL-safe: what the command generates unless --token or --no-token."""
    return secrets.token_urlsafe(32)


def is_loopback(host: str) -> bool:
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:  # a host name: only "localhost" is known to stay on this machine
        return False


def _canonical_name(name: str) -> str:
    """Lower case, IPv6 without brackets, IP literals in their shortest form."""
    name = name.lower()
    if name.startswith("[") and name.endswith("]"):
        name = name[1:-1]
    try:
        return ipaddress.ip_address(name).compressed
    except ValueError:
        return name


def netloc(name: str, port: int) -> str:
    """`name:port` as it appears in a Host header or an origin (IPv6 in brackets)."""
    name = _canonical_name(name)
    return f"[{name}]:{port}" if ":" in name else f"{name}:{port}"


def parse_host_header(value: str, default_port: int = 80) -> str | None:
    """The canonical `name:port` of a Host header, or None when it is malformed."""
    value = value.strip()
    if value.startswith("["):
        close = value.find("]")
        if close < 0:
            return None
        name, rest = value[: close + 1], value[close + 1:]
        if rest and not rest.startswith(":"):
            return None
        port_text = rest[1:] if rest else ""
    else:
        name, _, port_text = value.partition(":")
        if ":" in port_text:
            return None
    if not name or (port_text and not port_text.isdigit()) or len(port_text) > 5:
        return None
    return netloc(name, int(port_text) if port_text else default_port)


def normalise_origin(origin: str) -> str:
    """`scheme://name:port` with the scheme's default port made explicit; ValueError when it
    is not an http(s) origin (a path, a query, user info or a wildcard are not origins)."""
    parts = urlsplit(origin.strip())
    if parts.scheme not in DEFAULT_PORTS or not parts.hostname or parts.username or parts.password:
        raise ValueError(f"{origin!r} is not an origin like http://host:port")
    if parts.path not in ("", "/") or parts.query or parts.fragment or "*" in parts.netloc:
        raise ValueError(f"{origin!r} is not an origin: no path, query or wildcard")
    try:
        port = parts.port or DEFAULT_PORTS[parts.scheme]
    except ValueError:
        raise ValueError(f"{origin!r} has a bad port") from None
    return f"{parts.scheme}://{netloc(parts.hostname, port)}"


def host_names(bind_host: str) -> frozenset[str]:
    """Names a request may carry in Host: the loopback names and the bound host; bound to
    every interface, also this machine's own addresses and names."""
    names = {*LOOPBACK_NAMES, bind_host}
    if bind_host in WILDCARD_HOSTS:
        import psutil

        names.update(addr.address.split("%")[0] for addrs in psutil.net_if_addrs().values() for addr in addrs
                     if addr.family in (socket.AF_INET, socket.AF_INET6))
        names.update({socket.gethostname(), socket.getfqdn()})
    return frozenset(_canonical_name(n) for n in names if n)


@dataclass(frozen=True)
class Access:
    """The rules of one serving session (its port is the one really bound)."""

    port: int
    token: str | None  # None: --no-token (loopback only)
    hosts: frozenset[str]  # canonical `name:port` a request's Host may be
    extra_origins: frozenset[str] = frozenset()  # --allow-origin, normalised

    @classmethod
    def for_server(cls, bind_host: str, port: int, token: str | None, allow_origins: tuple[str, ...] = ()) -> Access:
        if token is None and not is_loopback(bind_host):
            raise ConfigError(f"--no-token is allowed on loopback only, not with --host {bind_host}")
        hosts = frozenset(netloc(name, port) for name in host_names(bind_host))
        return cls(port, token, hosts, frozenset(normalise_origin(o) for o in allow_origins))

    @property
    def cookie_name(self) -> str:
        # Cookies ignore ports: two servers on one machine need names of their own.
        return f"{COOKIE_PREFIX}{self.port}"

    @property
    def cookie_value(self) -> str:
        """Derived from the token (so any token fits a cookie, and the cookie is not the token)."""
        assert self.token is not None
        return hmac.new(self.token.encode("utf-8"), b"e3dpsm serve cookie", hashlib.sha256).hexdigest()

    def request_host(self, host_header: str | None) -> str | None:
        """The request's canonical `name:port` when Host names this server, else None."""
        if not host_header:
            return None
        canonical = parse_host_header(host_header)
        return canonical if canonical in self.hosts else None

    def origin_allowed(self, origin: str) -> bool:
        try:
            normalised = normalise_origin(origin)
        except ValueError:  # "null" (sandboxed frames, file:), or garbage
            return False
        scheme, _, rest = normalised.partition("://")
        return (scheme == "http" and rest in self.hosts) or normalised in self.extra_origins

    def token_verdict(self, query_token: str | None, cookie: str | None) -> int:
        """200 when the query's token or the cookie proves the token (or there is none),
        401 when neither is given, 403 when what is given is wrong. A query token is judged
        first: a stale cookie must not hide a mistyped URL, nor the reverse."""
        if self.token is None:
            return 200
        if query_token is not None:
            return 200 if hmac.compare_digest(query_token.encode("utf-8"), self.token.encode("utf-8")) else 403
        if cookie is not None:
            return 200 if hmac.compare_digest(cookie.encode("utf-8"), self.cookie_value.encode("utf-8")) else 403
        return 401


def csp_hash(inline: str) -> str:
    """The CSP source admitting exactly this inline <script> or <style> body (CSP level 2 hashes)."""
    return "'sha256-" + base64.b64encode(hashlib.sha256(inline.encode("utf-8")).digest()).decode("ascii") + "'"


def response_headers(host: str | None, page_hashes: tuple[str, str] | None) -> dict[str, str]:
    """Headers on every response. The page (`page_hashes`: its script's and its style's CSP
    hashes) may run only its own inline script and style and talk only to this server's
    socket at the Host it was loaded from; anything else may run and load nothing."""
    if page_hashes is not None and host is not None:
        script, style = page_hashes
        policy = (f"default-src 'none'; script-src {script}; style-src {style}; connect-src 'self' ws://{host}; "
                  "base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
    else:
        policy = "default-src 'none'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    return {"Content-Security-Policy": policy, "X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff",
            "Referrer-Policy": "no-referrer", "Cache-Control": "no-store"}


@dataclass
class Refusals:
    """Requests and clients refused, by rule: counted into the report (never the token)."""

    host: int = 0  # Host not this server (DNS rebinding)
    origin: int = 0  # /ws from a foreign Origin, or without one and without the token
    token_missing: int = 0  # 401
    token_wrong: int = 0  # 403
    rate_limited: int = 0  # clients closed for sending too many messages (1008)


@dataclass
class TokenBucket:
    """At most `rate` messages a second on average, bursts of `burst`: each message takes
    one token; tokens refill continuously up to `burst`."""

    rate: float
    burst: float
    clock: Callable[[], float] = time.monotonic
    tokens: float = field(init=False)
    stamp: float = field(init=False)

    def __post_init__(self) -> None:
        self.tokens, self.stamp = self.burst, self.clock()

    def take(self) -> bool:
        now = self.clock()
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True
