"""The `e3dpsm serve` protocol: every message type, both ways, in one place.

docs/serve.md documents these tables; tests/test_serve.py checks the fields. Server to
client: JSON text messages, each an object with a "type". Client to server: JSON text
objects of the types in CLIENT_MESSAGES; anything else (binary, not JSON, not an object, an
unknown type, a bad field) closes THAT client with one of the close codes below and a reason.

Times: `t_us` is stream time (the window end, microseconds, the recording's clock; with
--loop, later passes add the recording's span so it keeps increasing); `*_wall_ms` are the
server's wall clock (Unix epoch, ms), which a page on the same machine compares with
`performance.timeOrigin + performance.now()`.
"""
from __future__ import annotations

import base64
import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

PROTOCOL_VERSION = 1

# Close codes (RFC 6455 section 7.4.1) the server uses.
CLOSE_GOING_AWAY = 1001  # the server stops (Ctrl-C, --duration-s, end of the recording)
CLOSE_UNSUPPORTED = 1003  # a binary message: the protocol is JSON text only
CLOSE_INVALID = 1007  # text that is not a JSON object
CLOSE_POLICY = 1008  # an unknown type or a bad field
CLOSE_TOO_SLOW = 4000  # the client's pose backlog stayed over the bound (--client-backlog)

CLOSE_TOO_BIG = 1009  # a message over MAX_CLIENT_MESSAGE_BYTES (aiohttp closes it)

MAX_CLIENT_MESSAGE_BYTES = 64 * 1024
MAX_LATENCY_SAMPLES = 512  # per "latency" message
# A page sends a hello, then one latency report a second (a few more after its timers were
# throttled in a background tab): a client over this rate is flooding and is closed (1008).
CLIENT_MESSAGES_PER_S = 10.0
CLIENT_MESSAGE_BURST = 40


class ProtocolError(Exception):
    """A client message the server refuses; the client is closed with `code`."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        # A close reason must fit a control frame (125 bytes, 2 of them the code).
        self.reason = reason.encode("utf-8")[:120].decode("utf-8", "ignore")


def _dumps(message: dict[str, Any]) -> str:
    return json.dumps(message, separators=(",", ":"), allow_nan=False)


def _pose_list(pose: np.ndarray | None) -> list[list[float]] | None:
    if pose is None:
        return None
    return np.round(np.asarray(pose, dtype=np.float64), 3).tolist()


# ---- server -> client ------------------------------------------------------------------------------
def hello(*, joints: list[str], bones: list[tuple[int, int]], models: list[str], window_ms: float,
          sensor_hw: tuple[int, int], frame_hw: tuple[int, int], source: str, live: bool,
          ground_truth: bool, speed: float, client_id: int) -> str:
    return _dumps({
        "type": "hello", "protocol": PROTOCOL_VERSION, "client_id": client_id, "joints": joints,
        "bones": [list(b) for b in bones], "models": models, "window_ms": window_ms,
        "sensor_hw": list(sensor_hw), "frame_hw": list(frame_hw), "source": source, "live": live,
        "ground_truth": ground_truth, "speed": speed,
    })


@dataclass(frozen=True)
class PoseMessage:
    """One window's poses; `text` is what goes on the wire (built once for every client)."""

    seq: int
    t_us: int
    window_end_wall_ms: float
    text: str


def pose(*, seq: int, t_us: int, pose_mm: np.ndarray, compare_mm: np.ndarray | None, gt_mm: np.ndarray | None,
         window_end_wall_ms: float, sent_wall_ms: float, step_ms: float, compare_step_ms: float | None,
         events: int) -> PoseMessage:
    text = _dumps({
        "type": "pose", "seq": seq, "t_us": t_us, "pose": _pose_list(pose_mm), "compare": _pose_list(compare_mm),
        "gt": _pose_list(gt_mm), "window_end_wall_ms": round(window_end_wall_ms, 3),
        "sent_wall_ms": round(sent_wall_ms, 3), "step_ms": round(step_ms, 3),
        "compare_step_ms": None if compare_step_ms is None else round(compare_step_ms, 3), "events": events,
    })
    return PoseMessage(seq, t_us, window_end_wall_ms, text)


def frame(*, seq: int, t_us: int, lnes: np.ndarray, max_width: int) -> str:
    """The window's LNES [2, H, W] downscaled (block max) to at most `max_width` columns, as
    two uint8 planes (positive then negative; 0 = no event, 1..255 = time in the window),
    base64 of H*W*2 bytes, row-major, plane-interleaved per pixel."""
    channels, height, width = lnes.shape
    factor = max(1, math.ceil(width / max_width))
    h, w = height // factor, width // factor
    blocks = lnes[:, : h * factor, : w * factor].reshape(channels, h, factor, w, factor).max(axis=(2, 4))
    # An event at the very start of the window has LNES 0 but is an event: lift it to 1.
    scaled = np.where(blocks > 0, np.clip(np.rint(blocks * 254.0) + 1.0, 1.0, 255.0), 0.0).astype(np.uint8)
    data = np.ascontiguousarray(scaled.transpose(1, 2, 0))
    return _dumps({"type": "frame", "seq": seq, "t_us": t_us, "width": w, "height": h, "channels": channels,
                   "encoding": "uint8-base64", "data": base64.b64encode(data.tobytes()).decode("ascii")})


def stats(**fields: Any) -> str:
    return _dumps({"type": "stats", **fields})


def status(state: str, message: str) -> str:
    """`state`: one of STATUS_STATES; `message` a sentence for the page's status line."""
    if state not in STATUS_STATES:
        raise ValueError(f"unknown status state {state!r}")
    return _dumps({"type": "status", "state": state, "message": message})


STATUS_STATES = ("waiting", "running", "loop", "source stopped", "recording ended", "stopping")


def pong(client_t: float | None, server_wall_ms: float) -> str:
    return _dumps({"type": "pong", "t": client_t, "server_wall_ms": round(server_wall_ms, 3)})


# ---- client -> server ------------------------------------------------------------------------------
CLIENT_MESSAGES = ("ping", "latency", "hello")


@dataclass(frozen=True)
class LatencyReport:
    """What a page measured since its previous report."""

    samples_ms: tuple[float, ...]  # window end on the server's clock -> pose drawn, per pose
    received: int  # pose messages received so far
    drawn: int  # skeleton updates drawn so far (#pose-count)
    gaps: int  # poses missing between received seq numbers so far
    out_of_order: int  # poses whose seq was not above the previous one, so far


def _number(message: dict[str, Any], key: str, *, required: bool) -> float | None:
    value = message.get(key)
    if value is None and not required:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ProtocolError(CLOSE_POLICY, f"'{key}' must be a finite number")
    return float(value)


def _count(message: dict[str, Any], key: str) -> int:
    value = message.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ProtocolError(CLOSE_POLICY, f"'{key}' must be a non-negative integer")
    return value


def parse_client_message(text: str) -> tuple[str, Any]:
    """(type, payload) of a client text message, or ProtocolError.

    ping    {"type": "ping", "t": number?}              -> a "pong" echoing t
    latency {"type": "latency", "samples_ms": [number], "received": int, "drawn": int,
             "gaps": int, "out_of_order": int}          -> payload LatencyReport
    hello   {"type": "hello", "agent": string?}         -> payload the agent string (<= 200 chars)
    """
    try:
        message = json.loads(text)
    except ValueError:
        raise ProtocolError(CLOSE_INVALID, "not JSON") from None
    if not isinstance(message, dict):
        raise ProtocolError(CLOSE_INVALID, "a message must be a JSON object")
    kind = message.get("type")
    if kind not in CLIENT_MESSAGES:
        raise ProtocolError(CLOSE_POLICY, f"unknown message type {str(kind)[:40]!r}; expected one of "
                            f"{', '.join(CLIENT_MESSAGES)}")
    if kind == "ping":
        return kind, _number(message, "t", required=False)
    if kind == "hello":
        agent = message.get("agent", "")
        if not isinstance(agent, str):
            raise ProtocolError(CLOSE_POLICY, "'agent' must be a string")
        return kind, agent[:200]
    samples = message.get("samples_ms")
    if not isinstance(samples, list) or len(samples) > MAX_LATENCY_SAMPLES:
        raise ProtocolError(CLOSE_POLICY, f"'samples_ms' must be a list of at most {MAX_LATENCY_SAMPLES} numbers")
    values = []
    for value in samples:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ProtocolError(CLOSE_POLICY, "'samples_ms' must hold finite numbers")
        values.append(float(value))
    return kind, LatencyReport(tuple(values), _count(message, "received"), _count(message, "drawn"),
                               _count(message, "gaps"), _count(message, "out_of_order"))
