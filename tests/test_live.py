"""Live dv:// source on localhost: dv-processing's own NetworkWriter (in a publisher process)
replays a recording; the reader gets the same events, and `run` the same poses."""
from __future__ import annotations

import json
import re
import socket
import threading

import numpy as np
import pytest

from _runtime_helpers import exported_tiny, synthetic_stream
from e3dpsm.cli import main
from e3dpsm.data.readers import read_events, write_events_h5
from e3dpsm.data.sequence import EventStream
from e3dpsm.errors import DataError

pytest.importorskip("dv_processing", reason="dv-processing (pip extra cameras) is not installed")

from e3dpsm.data.live import open_live_source, publish_recording  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("live")
    x, y, t, p = synthetic_stream(seed=3)
    stream = EventStream(x.astype(np.int32), y.astype(np.int32), t, p.astype(np.uint8), sensor_hw=(480, 640))
    write_events_h5(folder / "events.h5", stream)
    return folder / "events.h5"


def test_live_source_gives_the_recordings_events_and_says_why_it_stopped(recording):
    want = read_events(recording)
    port = free_port()
    with publish_recording(recording, port, speed=0) as publisher:
        with open_live_source(f"dv://127.0.0.1:{port}") as source:
            assert source.sensor_hw == (480, 640)
            chunks = list(source)
        assert publisher.wait(30) == 0
    assert all(np.all(np.diff(c.t_us) >= 0) for c in chunks)
    for name in ("x", "y", "t_us", "p"):
        np.testing.assert_array_equal(np.concatenate([getattr(c, name) for c in chunks]), getattr(want, name))
    assert source.stopped_reason == f"publisher dv://127.0.0.1:{port} closed the stream after {len(want)} events"


def test_run_on_the_live_source_gives_the_recordings_poses(recording, tmp_path, tmp_path_factory):
    graph = exported_tiny(str(tmp_path_factory.getbasetemp()))[1]
    common = ["--model", str(graph), "--threads", "1", "--no-progress"]
    assert main(["run", *common, "--events", str(recording), "--out", str(tmp_path / "file.csv")]) == 0
    port = free_port()
    with publish_recording(recording, port, speed=0):
        code = main(["run", *common, "--events", f"dv://127.0.0.1:{port}", "--out", str(tmp_path / "live.csv")])
    assert code == 0
    want = (tmp_path / "file.csv").read_text()
    assert (tmp_path / "live.csv").read_text() == want and len(want.splitlines()) >= 9  # identical CSV
    live = json.loads((tmp_path / "live.report.json").read_text())["live"]
    assert live["stopped"].startswith("publisher") and live["events_received"] == len(read_events(recording))


@pytest.mark.parametrize("url, message", [
    ("dv:/127.0.0.1:7777", r"malformed live source 'dv:/127\.0\.0\.1:7777': expected dv://HOST:PORT"),
    ("dv://127.0.0.1:99999", "malformed live source"),
    ("dv://127.0.0.1:{port}", r"cannot connect to dv://127\.0\.0\.1:\d+: .*refused"),
])
def test_bad_url_or_nothing_listening_is_one_clear_line(url, message):
    with pytest.raises(DataError, match=message):
        open_live_source(url.format(port=free_port()), timeout_s=2)


def test_run_on_a_dead_live_source_fails_with_one_line_and_writes_nothing(tmp_path, tmp_path_factory, capsys):
    graph = exported_tiny(str(tmp_path_factory.getbasetemp()))[1]
    code = main(["run", "--model", str(graph), "--events", f"dv://127.0.0.1:{free_port()}",
                 "--out", str(tmp_path / "poses.csv")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "cannot connect to dv://127.0.0.1:" in err
    assert list(tmp_path.iterdir()) == []


# A publisher that stalls, drips, breaks off or sends damage: the source ends in bounded time ------

@pytest.fixture(scope="module")
def published_bytes(recording):
    """What dv-processing's NetworkWriter sends a client for the recording: (IO header part,
    packets part), split where the packets start."""
    port = free_port()
    data = bytearray()
    with publish_recording(recording, port, speed=0) as publisher:
        with socket.create_connection(("127.0.0.1", port), timeout=10) as client:
            client.settimeout(10)
            while chunk := client.recv(1 << 16):
                data += chunk
        assert publisher.wait(30) == 0
    header_end = 4 + int.from_bytes(data[:4], "little")
    assert data[4 + 4:4 + 8] == b"IOHE" and len(data) > header_end + 8
    return bytes(data[:header_end]), bytes(data[header_end:])


class ScriptedPublisher:
    """A TCP server that sends each client `data` (in `drip` pieces `pause_s` apart, if given),
    then holds the connection open (`then="stall"`) or closes it."""

    def __init__(self, data: bytes, then: str = "stall", drip: int = 0, pause_s: float = 0.0) -> None:
        self.data, self.then, self.drip, self.pause_s = data, then, drip, pause_s
        self._server = socket.create_server(("127.0.0.1", 0))
        self.url = f"dv://127.0.0.1:{self._server.getsockname()[1]}"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        self._server.settimeout(0.2)
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except OSError:
                continue
            with conn:
                step = self.drip or len(self.data) or 1
                for lo in range(0, len(self.data), step):
                    conn.sendall(self.data[lo:lo + step])
                    if self._stop.wait(self.pause_s):
                        return
                if self.then == "stall":
                    self._stop.wait(60)

    def __enter__(self) -> ScriptedPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        self._server.close()


@pytest.fixture(scope="module")
def bounded():
    from _bounded import BoundedWorker

    with BoundedWorker(preload=("e3dpsm.data.live", "_fuzz_targets")) as worker:
        yield worker


def test_a_server_that_accepts_and_sends_nothing_is_refused_within_the_timeout(bounded):
    """dv-processing's NetworkReader waited forever here, holding the GIL."""
    with ScriptedPublisher(b"") as server:
        outcome = bounded.call("_fuzz_targets:drain_live", server.url, 1.0, bound_s=20)
    assert outcome.kind == "refused", outcome
    assert outcome.detail == (f"DataError: {server.url}: connected, but no stream header came within 1 s; is a "
                              "dv-processing publisher (DV software, a camera) listening there?")
    assert outcome.seconds < 5


@pytest.mark.parametrize("drip", [0, 3])
def test_a_stream_that_stalls_ends_with_its_events_and_the_reason(bounded, published_bytes, recording, drip):
    """Everything sent, then silence: every event comes, then the stream ends after the timeout,
    also when the bytes trickle in a few at a time (the deadline counts, not each recv)."""
    header, packets = published_bytes
    with ScriptedPublisher(header + packets, "stall", drip=drip and 5000, pause_s=0.05 * bool(drip)) as server:
        outcome = bounded.call("_fuzz_targets:drain_live", server.url, 1.0, bound_s=60)
    assert outcome.kind == "returned", outcome
    events = len(read_events(recording))
    assert outcome.value == (events, f"no events from {server.url} for 1 s (after {events} events); stopped waiting")


def test_a_stream_dripping_one_byte_at_a_time_is_not_waited_on_forever(bounded, published_bytes):
    header, _ = published_bytes
    with ScriptedPublisher(header + b"\0\0\0\0\xff\0\0\0" + bytes(255), drip=1, pause_s=0.3) as server:
        outcome = bounded.call("_fuzz_targets:drain_live", server.url, 1.0, bound_s=30)
    assert outcome.kind == "refused" and "no stream header came within 1 s" in outcome.detail, outcome
    assert outcome.seconds < 5


def test_a_publisher_that_breaks_off_mid_packet_ends_the_stream(bounded, published_bytes):
    header, packets = published_bytes
    with ScriptedPublisher(header + packets[:100], "close") as server:
        outcome = bounded.call("_fuzz_targets:drain_live", server.url, 5.0, bound_s=30)
    assert outcome.kind == "returned", outcome
    assert outcome.value == (0, f"publisher {server.url} closed the stream (92 bytes into a packet, dropped) "
                                "after 0 events")


@pytest.mark.parametrize("damage, message", [
    (lambda p: p[:4] + (2**31 - 1).to_bytes(4, "little") + p[8:],
     r"corrupted stream at byte \d+: a packet header declares stream 0 and 2147483647 bytes \(at most 67108864\)"),
    (lambda p: p[:8] + (10**6).to_bytes(4, "little") + p[12:],
     r"corrupted packet at stream byte \d+: its FlatBuffer declares 1000000 bytes, \d+ decompressed"),
    (lambda p: p[:16] + b"XXXX" + p[20:], r"corrupted packet at stream byte 720: file identifier b'XXXX' at byte 4, "
                                           r"expected b'EVTS' \(byte 8 of the decompressed packet\)"),
])
def test_a_damaged_packet_is_one_error_line(bounded, published_bytes, damage, message):
    header, packets = published_bytes
    with ScriptedPublisher(header + damage(packets), "stall") as server:
        outcome = bounded.call("_fuzz_targets:drain_live", server.url, 5.0, bound_s=30)
    assert outcome.kind == "refused" and "\n" not in outcome.detail, outcome
    assert re.search(message, outcome.detail), outcome.detail


def test_run_on_a_silent_server_fails_with_one_line_and_writes_nothing(bounded, tmp_path, tmp_path_factory):
    graph = exported_tiny(str(tmp_path_factory.getbasetemp()))[1]
    with ScriptedPublisher(b"") as server:
        outcome = bounded.call("_fuzz_targets:run_cli", ["run", "--model", str(graph), "--events", server.url,
                               "--live-timeout-s", "1", "--out", str(tmp_path / "poses.csv")], bound_s=60)
    assert outcome.kind == "returned", outcome
    code, _, err = outcome.value
    assert code == 2 and err.splitlines() == [f"e3dpsm run: error: {server.url}: connected, but no stream header came "
                                              "within 1 s; is a dv-processing publisher (DV software, a camera) "
                                              "listening there?"]
    assert list(tmp_path.iterdir()) == []


def test_run_on_a_live_stream_whose_last_packet_jumps_an_hour_fails_with_one_line(bounded, published_bytes, tmp_path,
                                                                                     tmp_path_factory):
    """Corrupted timestamps in a live packet: `run` refuses the silence instead of stepping an
    hour of empty windows (--max-gap-s, the same check as for files)."""
    import struct

    from e3dpsm.data.formats.flatbuffer import root_table, vector

    header, packets = published_bytes
    data, at, last = bytearray(packets), 0, 0
    while at < len(data):  # the last packet
        last, at = at, at + 8 + struct.unpack_from("<i", data, at + 4)[0]
    table = root_table(bytes(data[last + 12:at]), b"EVTS")  # the payload without its size prefix
    start, count = vector(table, 0, 16)
    for k in range(count - 10, count):  # the last ten events an hour later
        offset = last + 12 + start + 16 * k
        struct.pack_into("<q", data, offset, struct.unpack_from("<q", data, offset)[0] + 3_600_000_000)
    graph = exported_tiny(str(tmp_path_factory.getbasetemp()))[1]
    with ScriptedPublisher(header + bytes(data), "close") as server:
        outcome = bounded.call("_fuzz_targets:run_cli", ["run", "--model", str(graph), "--events", server.url,
                               "--out", str(tmp_path / "poses.csv"), "--threads", "1"], bound_s=60)
    assert outcome.kind == "returned", outcome
    code, _, err = outcome.value
    assert code == 2 and len(err.splitlines()) == 1, err
    assert re.match(rf"e3dpsm run: error: {server.url}: events \d+ and \d+ are 3600 s apart: 180,000 empty", err)
    assert list(tmp_path.iterdir()) == []
