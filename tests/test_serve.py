"""`e3dpsm serve`: the protocol, the poses against `e3dpsm run`, security, slow and bad clients,
Ctrl-C and the report. The server runs as a subprocess (as users run it); clients are aiohttp."""
from __future__ import annotations

import asyncio
import base64
import json
import socket
from pathlib import Path

import aiohttp
import numpy as np
import pytest

from _runtime_helpers import WINDOW_US, exported_tiny
from _serve_helpers import ServerProcess, write_recording
from e3dpsm.cli import main
from e3dpsm.serve import protocol
from e3dpsm.serve.clients import ClientChannel
from e3dpsm.serve.source import RecordingReplay

WINDOWS = 30  # 0.6 s of recording


@pytest.fixture(scope="module")
def graph(tmp_path_factory) -> Path:
    return exported_tiny(str(tmp_path_factory.getbasetemp()))[1]


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return write_recording(tmp_path_factory.mktemp("serve_rec") / "seq", WINDOWS)


async def _collect(url: str, *, send_after_hello: str | bytes | None = None) -> tuple[list[dict], int | None]:
    """Every message until the server closes the socket; (messages, close code)."""
    messages: list[dict] = []
    async with aiohttp.ClientSession() as session:
        async with session.ws_connect(url) as ws:
            async for msg in ws:
                if msg.type != aiohttp.WSMsgType.TEXT:
                    break
                messages.append(json.loads(msg.data))
                if messages[-1]["type"] == "hello" and send_after_hello is not None:
                    if isinstance(send_after_hello, bytes):
                        await ws.send_bytes(send_after_hello)
                    else:
                        await ws.send_str(send_after_hello)
            return messages, ws.close_code


def _stalled_client(port: int, token: str) -> socket.socket:
    """A WebSocket client that completes the handshake and then never reads a byte."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
    sock.connect(("127.0.0.1", port))
    key = base64.b64encode(b"0123456789abcdef").decode()
    sock.sendall((f"GET /ws?token={token} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                  f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:  # the 101 answer: from here on, nothing is read
        head += sock.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    return sock


def _run_csv(graph: Path, recording: Path, out: Path) -> tuple[np.ndarray, np.ndarray]:
    assert main(["run", "--model", str(graph), "--events", str(recording), "--out", str(out), "--no-progress"]) == 0
    table = np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2)
    return table[:, 0].astype(np.int64), table[:, 1:].reshape(-1, 16, 3)


# ---- the command's own checks (in process, nothing bound) -------------------------------------------
@pytest.mark.parametrize("option", [["--speed", "0"], ["--threads", "0"], ["--client-backlog", "0"],
                                    ["--port", "70000"], ["--duration-s", "nan"], ["--token", " "],
                                    ["--allow-origin", "*"], ["--allow-origin", "http://viewer.example/page"]])
def test_bad_option_values_fail_with_one_line(capsys, option):
    try:
        code = main(["serve", "--model", "none.onnx", "--source", "none.h5", *option])
    except SystemExit as exc:  # an argument argparse refuses (a type check), in one line too
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("e3dpsm serve: error:") and option[0] in err[0]


def test_live_source_fails_with_one_line_when_it_cannot_open(capsys, graph, tmp_path):
    # Before the live reader is merged: "this install has no live event reader"; after: its DataError.
    assert main(["serve", "--model", str(graph), "--source", "dv://127.0.0.1:1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("e3dpsm serve: error:") and "dv://127.0.0.1:1" in err[0]


def test_a_port_in_use_fails_with_one_line(capsys, graph, recording, tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        assert main(["serve", "--model", str(graph), "--source", str(recording), "--port", str(port),
                     "--out", str(tmp_path / "report")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"e3dpsm serve: error: cannot listen on 127.0.0.1:{port}: Address already in use"]
    assert not (tmp_path / "report" / "serve.report.json").exists()


# ---- pieces, against independent references ----------------------------------------------------------
@pytest.mark.parametrize("text, code", [
    ("not json", protocol.CLOSE_INVALID), ("[1, 2]", protocol.CLOSE_INVALID),
    ('{"type": "shout"}', protocol.CLOSE_POLICY), ('{"no": "type"}', protocol.CLOSE_POLICY),
    ('{"type": "ping", "t": "soon"}', protocol.CLOSE_POLICY),
    ('{"type": "latency", "samples_ms": [1, NaN], "received": 1, "drawn": 1, "gaps": 0, "out_of_order": 0}',
     protocol.CLOSE_POLICY),
    ('{"type": "latency", "samples_ms": [1], "received": -1, "drawn": 1, "gaps": 0, "out_of_order": 0}',
     protocol.CLOSE_POLICY),
    ('{"type": "latency", "samples_ms": [1], "drawn": 1, "gaps": 0, "out_of_order": 0}', protocol.CLOSE_POLICY),
])
def test_malformed_client_messages_are_refused_with_their_close_code(text, code):
    with pytest.raises(protocol.ProtocolError) as info:
        protocol.parse_client_message(text)
    assert info.value.code == code and len(info.value.reason.encode()) <= 123


def test_valid_client_messages_parse():
    assert protocol.parse_client_message('{"type": "ping", "t": 12.5}') == ("ping", 12.5)
    kind, report = protocol.parse_client_message(
        '{"type": "latency", "samples_ms": [3, 4.5], "received": 9, "drawn": 8, "gaps": 1, "out_of_order": 0}')
    assert kind == "latency" and report.samples_ms == (3.0, 4.5) and (report.received, report.drawn, report.gaps) == (9, 8, 1)


def test_frame_message_is_the_block_max_of_the_lnes():
    rng = np.random.default_rng(0)
    lnes = ((rng.random((2, 192, 256)) < 0.05) * rng.random((2, 192, 256))).astype(np.float32)
    lnes[0, 0, 0] = 0.0  # nothing else in that 2x2 block of channel 0 must light it
    lnes[0, 0:2, 0:2] = 0.0
    m = json.loads(protocol.frame(seq=3, t_us=9, lnes=lnes, max_width=128))
    assert (m["width"], m["height"], m["channels"]) == (128, 96, 2)
    got = np.frombuffer(base64.b64decode(m["data"]), np.uint8).reshape(96, 128, 2)
    for c in range(2):
        for r, q in [(0, 0), (5, 7), (95, 127), (40, 60)]:
            block = float(lnes[c, 2 * r:2 * r + 2, 2 * q:2 * q + 2].max())  # explicit loop reference
            expect = 0 if block == 0 else min(255, int(np.rint(block * 254)) + 1)
            assert got[r, q, c] == expect
    assert (got > 0).sum() == sum((lnes[c].reshape(96, 2, 128, 2).max(axis=(1, 3)) > 0).sum() for c in range(2))


def _pose(seq: int) -> protocol.PoseMessage:
    return protocol.PoseMessage(seq, seq * WINDOW_US, 0.0, f'{{"seq":{seq}}}')


def test_a_full_pose_queue_drops_its_oldest_and_keeps_order():
    async def scenario():
        channel = ClientChannel(0, "test", pose_backlog=3)
        for seq in range(10):
            channel.put_pose(_pose(seq))
        channel.put_frame("f1")
        channel.put_frame("f2")  # replaces f1 unsent
        channel.put_control("c")
        return channel, [await channel.next_message() for _ in range(5)]

    channel, got = asyncio.run(scenario())
    assert [(kind, text) for kind, text, _ in got] == [
        ("control", "c"), ("pose", '{"seq":7}'), ("pose", '{"seq":8}'), ("pose", '{"seq":9}'), ("frame", "f2")]
    assert (channel.poses_dropped, channel.frames_dropped) == (7, 1)


def test_clients_that_come_and_go_leave_a_bounded_hub_and_every_latency_counted():
    from e3dpsm.serve.clients import MAX_LISTED_CLOSED, ClientHub

    async def scenario():
        hub = ClientHub(pose_backlog=10)
        staying = hub.add("stays")
        for seq in range(MAX_LISTED_CLOSED + 50):  # one client per pose, gone after it
            visitor = hub.add(f"visitor {seq}")
            message = _pose(seq)
            hub.broadcast_pose(message)
            for channel in (staying, visitor):
                kind, text, pose = await channel.next_message()
                channel.sent(kind, pose)
            visitor.closed(1000, None)
            hub.retire(visitor)
        return hub, staying

    hub, staying = asyncio.run(scenario())
    visits = MAX_LISTED_CLOSED + 50
    assert list(hub.open) == [0] and hub.seen == visits + 1 and hub.retired == visits
    listed = hub.summaries()
    assert [c["client_id"] for c in listed] == [0, *range(visits + 1 - MAX_LISTED_CLOSED, visits + 1)]  # the latest
    assert all(c["poses_sent"] == 1 for c in listed[1:]) and staying.poses_sent == visits
    assert hub.latency_ms("sent").count == 2 * visits  # the unlisted visitors' latencies are still counted


def test_replay_releases_every_event_once_on_its_schedule(recording):
    from e3dpsm.data.readers import read_events

    stream = read_events(recording)
    speed = 200.0
    replay = RecordingReplay(stream, WINDOW_US, speed=speed)

    async def ticks():
        return [tick async for tick in replay.ticks()]

    got = asyncio.run(ticks())
    t = np.concatenate([tick.chunk[2] for tick in got if tick.chunk is not None])
    np.testing.assert_array_equal(t, stream.t_us)  # all, once, in order
    t0 = int(stream.t_us[0])
    flushes = [tick.flush_until_us for tick in got if tick.flush_until_us is not None]
    assert flushes == [t0 + k * WINDOW_US for k in range(1, len(flushes) + 1)] and len(flushes) == WINDOWS - 1
    for tick, until in zip(got, range(t0 + replay.tick_us, 10**12, replay.tick_us)):
        if tick.chunk is not None:  # released only once the wall clock passed the slice's end
            assert tick.chunk[2].max() < until
    gaps = np.diff([tick.wall_ms for tick in got])
    np.testing.assert_allclose(gaps, replay.tick_us / 1e3 / speed, rtol=0, atol=1e-3)  # epoch ms: float64 steps of 2.4e-4
    assert got[-1].finish and not any(tick.finish for tick in got[:-1])


# ---- the server, end to end -----------------------------------------------------------------------------
def test_poses_match_run_and_the_report_says_what_happened(graph, recording, tmp_path):
    t_ref, pose_ref = _run_csv(graph, recording, tmp_path / "run.csv")
    out = tmp_path / "report"
    with ServerProcess(["--model", str(graph), "--source", str(recording), "--speed", "3", "--wait-clients", "1",
                        "--threads", "1", "--compare", str(graph), "--out", str(out)]) as server:
        messages, code = asyncio.run(_collect(server.ws))
        rc, stdout, stderr = server.wait()
    assert rc == 0, stderr
    hello = messages[0]
    assert hello["type"] == "hello" and hello["joints"][0] == "Head" and len(hello["joints"]) == 16
    assert hello["window_ms"] == 20 and hello["ground_truth"] is True and hello["live"] is False
    assert sorted(map(tuple, hello["bones"])) == sorted((c, p) for c, p in enumerate(
        (0, 0, 1, 2, 3, 1, 5, 6, 2, 8, 9, 10, 5, 12, 13, 14)) if c != p)
    poses = [m for m in messages if m["type"] == "pose"]
    assert [m["seq"] for m in poses] == list(range(len(poses)))
    t = np.array([m["t_us"] for m in poses])
    np.testing.assert_array_equal(t, t_ref)  # the same windows as `e3dpsm run`
    assert np.all(np.diff(t) == WINDOW_US)
    # 3 decimals on the wire, 4 in the CSV: equal within 1e-3 mm
    np.testing.assert_allclose(np.array([m["pose"] for m in poses]), pose_ref, rtol=0, atol=1.1e-3)
    # --compare: the same graph on the same events, stepped on its own thread and state
    np.testing.assert_array_equal(np.array([m["compare"] for m in poses]), np.array([m["pose"] for m in poses]))
    assert hello["models"] == [graph.name, graph.name] and all(m["compare_step_ms"] > 0 for m in poses)
    gt = np.load(recording.parent / "gt.npz")
    for m in poses:  # the ground truth of the pose's own window end, in mm
        k = int(np.flatnonzero(gt["t_us"] == m["t_us"])[0])
        np.testing.assert_allclose(m["gt"], gt["j3d_m"][k] * 1000.0, atol=1e-3)
    assert all(m["window_end_wall_ms"] <= m["sent_wall_ms"] for m in poses)
    statuses = [m["state"] for m in messages if m["type"] == "status"]
    assert statuses[-1] == "recording ended" and code == protocol.CLOSE_GOING_AWAY
    assert any(m["type"] == "frame" for m in messages)

    report = json.loads((out / "serve.report.json").read_text())
    assert report["command"] == "serve" and report["stop_reason"] == "recording ended"
    assert report["poses"] == len(poses) and report["clients_seen"] == 1 and report["clients_not_listed"] == 0
    assert report["drops"] == {"0": {"poses": 0, "frames": report["clients"][0]["frames_dropped"]}}
    assert report["clients"][0]["poses_sent"] == len(poses) and report["clients"][0]["last_seq_sent"] == len(poses) - 1
    assert report["step_ms"]["count"] == len(poses) and report["latency_ms"]["sent"]["count"] == len(poses)
    assert "isa" in report["machine"] and report["config"]["speed"] == 3
    assert report["rss_mb"]["start"] > 0 and report["rss_mb"]["end"] > 0


def test_a_stalled_client_and_bad_clients_do_not_stop_a_good_one(graph, tmp_path):
    recording = write_recording(tmp_path / "long", 150, seed=5)  # 3 s: the stalled socket fills up
    out = tmp_path / "report"
    with ServerProcess(["--model", str(graph), "--source", str(recording), "--wait-clients", "4", "--threads", "1",
                        "--client-backlog", "5", "--frame-hz", "50", "--out", str(out)]) as server:
        stalled = _stalled_client(server.port, server.token)

        async def clients():
            good = asyncio.create_task(_collect(server.ws))
            await asyncio.sleep(0.3)  # connect order = client ids: stalled 0, good 1, then the bad ones
            bad_type = asyncio.create_task(_collect(server.ws, send_after_hello='{"type": "shout"}'))
            await asyncio.sleep(0.3)
            bad_binary = asyncio.create_task(_collect(server.ws, send_after_hello=b"\x00\x01"))
            return await asyncio.gather(good, bad_type, bad_binary)

        (good, good_code), (_, type_code), (_, binary_code) = asyncio.run(clients())
        rc, _, stderr = server.wait()
        stalled.close()
    assert rc == 0, stderr
    assert (type_code, binary_code) == (protocol.CLOSE_POLICY, protocol.CLOSE_UNSUPPORTED)
    report = json.loads((out / "serve.report.json").read_text())
    seqs = [m["seq"] for m in good if m["type"] == "pose"]
    assert seqs == list(range(report["poses"])) and report["poses"] >= 140 and good_code == protocol.CLOSE_GOING_AWAY
    by_id = {c["client_id"]: c for c in report["clients"]}
    assert by_id[1]["poses_dropped"] == 0 and by_id[1]["poses_sent"] == report["poses"]
    assert by_id[0]["poses_dropped"] > 0  # the stalled one: its oldest poses went, it never slowed client 1
    assert by_id[0]["poses_sent"] + by_id[0]["poses_dropped"] + by_id[0]["pose_backlog_at_end"] == report["poses"]
    assert (by_id[2]["close_code"], by_id[3]["close_code"]) == (protocol.CLOSE_POLICY, protocol.CLOSE_UNSUPPORTED)
    assert "shout" in by_id[2]["close_reason"]


class _FakeLive:
    """The live-source interface (e3dpsm.data.live): sensor_hw, EventStream chunks, close; it
    raises DataError "... stopped ..." after its chunks, as a publisher that goes away."""

    def __init__(self, stream, chunk: int) -> None:
        self.sensor_hw, self.stream, self.chunk, self.closed = stream.sensor_hw, stream, chunk, 0

    def __iter__(self):
        from e3dpsm.data.sequence import EventStream
        from e3dpsm.errors import DataError

        s = self.stream
        for lo in range(0, len(s), self.chunk):
            hi = lo + self.chunk
            yield EventStream(x=s.x[lo:hi], y=s.y[lo:hi], t_us=s.t_us[lo:hi], p=s.p[lo:hi], sensor_hw=s.sensor_hw)
        raise DataError("dv://fake: the publisher stopped")

    def close(self) -> None:
        self.closed += 1


def test_a_live_source_streams_every_pose_and_the_page_hears_it_stopped(graph, recording, tmp_path):
    from e3dpsm.data.readers import read_events
    from e3dpsm.runtime import StepSession
    from e3dpsm.serve.clients import ClientHub
    from e3dpsm.serve.estimator import ServeEngine
    from e3dpsm.serve.server import ServeConfig, serve
    from e3dpsm.serve.source import LiveFeed

    # The last event on the last microsecond of a window: only the end-of-stream close emits it.
    s = read_events(recording)
    end = int(s.t_us[0]) + 20 * WINDOW_US
    keep = s.t_us < end - 1
    edge = tmp_path / "edge.npz"
    np.savez(edge, x=np.append(s.x[keep], 5), y=np.append(s.y[keep], 5), t=np.append(s.t_us[keep], end - 1),
             p=np.append(s.p[keep], 1))
    t_ref, pose_ref = _run_csv(graph, edge, tmp_path / "run.csv")
    assert t_ref[-1] == end
    fake = _FakeLive(read_events(edge), chunk=777)
    feed = LiveFeed(fake)
    config = ServeConfig(model=str(graph), source="dv://fake", out=str(tmp_path / "report"), port=0, wait_clients=1,
                         token="live-test-token")

    async def scenario():
        hub = ClientHub(config.client_backlog)
        engine = ServeEngine(feed, hub, StepSession(graph, threads=1), window_ms=20.0)
        hello = {"joints": [], "bones": [], "models": ["m"], "window_ms": 20.0, "sensor_hw": fake.sensor_hw,
                 "frame_hw": (192, 256), "source": "dv://fake", "live": True, "ground_truth": False, "speed": 1.0}
        lines: list[str] = []
        server = asyncio.create_task(serve(config, feed, engine, hub, hello, {}, announce=lines.append))
        while not lines:
            await asyncio.sleep(0.01)
        got = await _collect(lines[0].split()[1].replace("/?token=", "/ws?token="))
        return await server, got, hub

    report, (messages, code), hub = asyncio.run(scenario())
    assert hub.open == {} and hub.retired == hub.seen == 1  # the closed client left the hub
    poses = [m for m in messages if m["type"] == "pose"]
    np.testing.assert_array_equal([m["t_us"] for m in poses], t_ref)
    np.testing.assert_allclose(np.array([m["pose"] for m in poses]), pose_ref, rtol=0, atol=1.1e-3)
    status = [m for m in messages if m["type"] == "status"][-1]
    assert status["state"] == "source stopped" and "publisher stopped" in status["message"]
    assert code == protocol.CLOSE_GOING_AWAY and report["stop_reason"] == "source stopped" and fake.closed == 1


def test_serve_on_a_real_dv_stream_gives_the_recordings_poses(graph, recording, tmp_path):
    """dv-processing's own NetworkWriter (publish_recording) feeds `serve --source dv://...`:
    the page gets the poses `e3dpsm run` writes for the recording, every one, in order."""
    pytest.importorskip("dv_processing", reason="dv-processing (pip extra cameras) is not installed")
    from e3dpsm.data.live import publish_recording
    from test_live import free_port

    t_ref, pose_ref = _run_csv(graph, recording, tmp_path / "run.csv")
    port = free_port()
    with publish_recording(recording, port, speed=1.0):
        with ServerProcess(["--model", str(graph), "--source", f"dv://127.0.0.1:{port}", "--wait-clients", "1",
                            "--threads", "1", "--out", str(tmp_path / "report")]) as server:
            messages, code = asyncio.run(_collect(server.ws))
            rc, _, stderr = server.wait()
    assert rc == 0, stderr
    assert messages[0]["type"] == "hello" and messages[0]["live"] is True
    poses = [m for m in messages if m["type"] == "pose"]
    assert [m["seq"] for m in poses] == list(range(len(poses)))
    np.testing.assert_array_equal([m["t_us"] for m in poses], t_ref)
    np.testing.assert_allclose(np.array([m["pose"] for m in poses]), pose_ref, rtol=0, atol=1.1e-3)
    assert [m for m in messages if m["type"] == "status"][-1]["state"] == "source stopped"
