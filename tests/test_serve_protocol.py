"""e3dpsm/serve/protocol.py against its specifications: the field tables, limits and close
codes of docs/serve.md (what page authors read), RFC 6455's close codes and control-frame
size, JSON's refusal of NaN, and an explicit loop for the event-frame image. No server runs
here: these are the messages' own contracts (the server's use of them: tests/test_serve.py)."""
from __future__ import annotations

import base64
import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from e3dpsm.serve import protocol

SERVE_DOC = (Path(__file__).resolve().parents[1] / "docs" / "serve.md").read_text(encoding="utf-8")


def _section(heading: str) -> str:
    """The text of docs/serve.md from the heading that starts with `heading` to the next heading."""
    start = SERVE_DOC.index(heading)
    end = SERVE_DOC.find("\n#", start + len(heading))
    return SERVE_DOC[start:end if end > 0 else None]


def _documented_fields(heading: str, table: int = 0) -> set[str]:
    """Every back-quoted name in the first column of the `table`-th field table of a section."""
    tables = re.split(r"\n\s*\n", _section(heading))
    rows = [t for t in tables if t.lstrip().startswith("| field")][table].splitlines()[2:]
    return {name for row in rows for name in re.findall(r"`([^`]+)`", row.split("|")[1])}


def _hello() -> dict:
    return json.loads(protocol.hello(joints=["head", "neck"], bones=[(1, 0)], models=["a.onnx", "b.onnx"],
                                     window_ms=20.0, sensor_hw=(480, 640), frame_hw=(192, 256), source="rec.h5",
                                     live=False, ground_truth=True, speed=2.0, client_id=7))


def _pose(**changes) -> protocol.PoseMessage:
    fields = dict(seq=4, t_us=80_000, pose_mm=np.full((16, 3), 1.23456), compare_mm=None,
                  gt_mm=np.zeros((16, 3)), window_end_wall_ms=1700000000123.45678, sent_wall_ms=1700000000130.0004,
                  step_ms=6.54321, compare_step_ms=None, events=321)
    return protocol.pose(**{**fields, **changes})


# ---- server to client: the documented fields, no more and no fewer -----------------------------------
def test_hello_carries_the_documented_fields_and_version() -> None:
    message = _hello()
    assert set(message) == {"type"} | _documented_fields("### Server to client: `hello`")
    assert message["type"] == "hello" and message["protocol"] == 1 == protocol.PROTOCOL_VERSION  # "(1)" in the doc
    assert message["bones"] == [[1, 0]] and message["sensor_hw"] == [480, 640] and message["frame_hw"] == [192, 256]
    assert (message["client_id"], message["models"], message["window_ms"], message["source"], message["live"],
            message["ground_truth"], message["speed"], message["joints"]) == (
        7, ["a.onnx", "b.onnx"], 20.0, "rec.h5", False, True, 2.0, ["head", "neck"])


def test_pose_carries_the_documented_fields_rounded_to_a_thousandth() -> None:
    built = _pose()
    message = json.loads(built.text)
    assert set(message) == {"type"} | _documented_fields("### Server to client: `pose`")
    assert (message["type"], message["seq"], message["t_us"], message["events"]) == ("pose", 4, 80_000, 321)
    assert message["pose"] == [[1.235] * 3] * 16 and message["gt"] == [[0.0] * 3] * 16 and message["compare"] is None
    assert (message["window_end_wall_ms"], message["sent_wall_ms"], message["step_ms"]) == (
        1700000000123.457, 1700000000130.0, 6.543)
    assert message["compare_step_ms"] is None
    assert json.loads(_pose(compare_mm=np.ones((16, 3)), compare_step_ms=2.00049).text)["compare_step_ms"] == 2.0
    assert json.loads(_pose(compare_mm=np.ones((16, 3)), compare_step_ms=2.00049).text)["compare"] == [[1.0] * 3] * 16
    assert (built.seq, built.t_us, built.window_end_wall_ms) == (4, 80_000, 1700000000123.45678)
    with pytest.raises(dataclasses.FrozenInstanceError):
        built.seq = 5


def test_a_pose_that_is_not_a_number_is_refused_not_sent_as_invalid_json() -> None:
    """JSON (RFC 8259) has no NaN: a page's JSON.parse would throw on Python's `NaN` token."""
    with pytest.raises(ValueError):
        _pose(pose_mm=np.full((16, 3), np.nan))


def test_frame_carries_the_documented_fields_and_every_pixel_of_the_block_max() -> None:
    rng = np.random.default_rng(1)
    lnes = ((rng.random((2, 12, 20)) < 0.4) * rng.random((2, 12, 20))).astype(np.float32)
    lnes[1, 0, 0] = 1.0
    lnes[0, 0:3, 3:6] = 0.0
    lnes[0, 1, 4] = 1e-6  # an event at the window's very start is still an event
    message = json.loads(protocol.frame(seq=2, t_us=40, lnes=lnes, max_width=7))
    assert set(message) == {"type"} | _documented_fields("### Server to client: `frame`")
    factor = 3  # ceil(20 / 7)
    assert (message["type"], message["seq"], message["t_us"], message["encoding"]) == ("frame", 2, 40, "uint8-base64")
    assert (message["height"], message["width"], message["channels"]) == (4, 6, 2)
    got = np.frombuffer(base64.b64decode(message["data"]), np.uint8).reshape(4, 6, 2)
    for c in range(2):
        for r in range(4):
            for q in range(6):
                block = float(lnes[c, factor * r:factor * (r + 1), factor * q:factor * (q + 1)].max())
                assert got[r, q, c] == (0 if block == 0 else int(np.rint(block * 254)) + 1), (c, r, q)
    assert got[0, 1, 0] == 1 and got[0, 0, 1] == 255
    small = json.loads(protocol.frame(seq=0, t_us=0, lnes=lnes[:, :4, :6], max_width=7))
    assert (small["height"], small["width"]) == (4, 6)  # narrower than the bound: not downscaled


def test_stats_status_and_pong_carry_the_documented_fields() -> None:
    stats = json.loads(protocol.stats(poses=3, server_hz=50))
    assert stats == {"type": "stats", "poses": 3, "server_hz": 50}
    states = re.findall(r"`([^`]+)`", next(row for row in _section("### Server to client: `stats`").splitlines()
                                           if row.startswith("| `state`")).split("|")[3])
    assert list(protocol.STATUS_STATES) == states
    for state in states:
        message = json.loads(protocol.status(state, "why"))
        assert message == {"type": "status", "state": state, "message": "why"}
        assert set(message) == {"type"} | _documented_fields("### Server to client: `stats`", table=1)
    with pytest.raises(ValueError) as info:
        protocol.status("paused", "no")
    assert str(info.value) == "unknown status state 'paused'"
    assert "`pong` answers `ping`: `t` (echoed), `server_wall_ms`" in SERVE_DOC
    assert json.loads(protocol.pong(12.5, 99.12345)) == {"type": "pong", "t": 12.5, "server_wall_ms": 99.123}


# ---- limits and close codes: docs/serve.md and RFC 6455 -----------------------------------------------
def test_close_codes_are_rfc_6455s_and_the_documented_ones() -> None:
    """RFC 6455 section 7.4.1: 1001 going away, 1003 data it cannot accept, 1007 data not
    consistent with the message type, 1008 policy violation, 1009 too big; 4000-4999 private."""
    assert (protocol.CLOSE_GOING_AWAY, protocol.CLOSE_UNSUPPORTED, protocol.CLOSE_INVALID, protocol.CLOSE_POLICY,
            protocol.CLOSE_TOO_BIG) == (1001, 1003, 1007, 1008, 1009)
    assert 4000 <= protocol.CLOSE_TOO_SLOW <= 4999 and protocol.CLOSE_TOO_SLOW == 4000
    table = re.findall(r"^\| (\d{4}) \|", SERVE_DOC, flags=re.MULTILINE)
    assert table == ["1001", "1003", "1007", "1008", "1009"]


def test_message_limits_are_the_documented_ones() -> None:
    kib = re.search(r"at most (\d+) KiB each \(larger: closed with 1009\)", SERVE_DOC)
    rate = re.search(r"at most (\d+) a second on average in bursts of (\d+)", SERVE_DOC)
    samples = re.search(r"`samples_ms` \(\[number\], at most (\d+)\)", SERVE_DOC)
    assert protocol.MAX_CLIENT_MESSAGE_BYTES == int(kib.group(1)) * 1024
    assert (protocol.CLIENT_MESSAGES_PER_S, protocol.CLIENT_MESSAGE_BURST) == (float(rate.group(1)),
                                                                               int(rate.group(2)))
    assert protocol.MAX_LATENCY_SAMPLES == int(samples.group(1))


def test_a_close_reason_fits_a_control_frame_and_stays_utf8() -> None:
    """A close frame's payload is at most 125 bytes, 2 of them the code (RFC 6455 5.5): the
    reason is cut to 120 bytes, never inside a character."""
    assert protocol.ProtocolError(1008, "x" * 300).reason == "x" * 120
    cut = protocol.ProtocolError(1008, "x" + "é" * 100).reason
    assert cut == "x" + "é" * 59 and len(cut.encode("utf-8")) == 119
    assert str(protocol.ProtocolError(1008, "short")) == "short" and protocol.ProtocolError(1007, "y").code == 1007


# ---- client to server -----------------------------------------------------------------------------------
def _latency(**changes) -> str:
    fields = {"type": "latency", "samples_ms": [1.5, 2], "received": 3, "drawn": 2, "gaps": 1, "out_of_order": 0}
    return json.dumps({**fields, **changes})


def test_client_messages_are_the_documented_types() -> None:
    rows = _section("### Client to server").split("| close code")[0]
    assert set(protocol.CLIENT_MESSAGES) == set(re.findall(r"^\| `(\w+)` \|", rows, flags=re.MULTILINE))
    assert protocol.parse_client_message('{"type": "hello", "agent": "page/1"}') == ("hello", "page/1")
    assert protocol.parse_client_message('{"type": "hello"}') == ("hello", "")
    assert protocol.parse_client_message(json.dumps({"type": "hello", "agent": "a" * 300})) == ("hello", "a" * 200)
    assert protocol.parse_client_message('{"type": "ping"}') == ("ping", None)
    assert protocol.parse_client_message('{"type": "ping", "t": 3}') == ("ping", 3.0)
    kind, report = protocol.parse_client_message(_latency(samples_ms=[0.5] * 512))
    assert kind == "latency" and report == protocol.LatencyReport((0.5,) * 512, 3, 2, 1, 0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        report.drawn = 9


@pytest.mark.parametrize("text, code, reason", [
    ("not json", 1007, "not JSON"),
    ("[1, 2]", 1007, "a message must be a JSON object"),
    ('{"type": "shout"}', 1008, "unknown message type 'shout'; expected one of ping, latency, hello"),
    (json.dumps({"type": "s" * 60}), 1008, f"unknown message type {'s' * 40!r}; expected one of ping, latency, hello"),
    ('{"type": "ping", "t": true}', 1008, "'t' must be a finite number"),
    ('{"type": "ping", "t": "soon"}', 1008, "'t' must be a finite number"),
    ('{"type": "hello", "agent": 5}', 1008, "'agent' must be a string"),
    (_latency(samples_ms=[0.5] * 513), 1008, "'samples_ms' must be a list of at most 512 numbers"),
    (_latency(samples_ms="1, 2"), 1008, "'samples_ms' must be a list of at most 512 numbers"),
    (_latency(samples_ms=None), 1008, "'samples_ms' must be a list of at most 512 numbers"),
    (_latency(samples_ms=[1, True]), 1008, "'samples_ms' must hold finite numbers"),
    (_latency(samples_ms=[1, "2"]), 1008, "'samples_ms' must hold finite numbers"),
    (_latency(received=True), 1008, "'received' must be a non-negative integer"),
    (_latency(gaps=1.0), 1008, "'gaps' must be a non-negative integer"),
    (_latency(out_of_order=-1), 1008, "'out_of_order' must be a non-negative integer"),
])
def test_each_bad_client_message_is_refused_with_its_code_and_reason(text, code, reason) -> None:
    with pytest.raises(protocol.ProtocolError) as info:
        protocol.parse_client_message(text)
    assert (info.value.code, info.value.reason) == (code, reason)
