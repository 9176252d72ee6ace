"""Live event streams: `dv://host:port`, dv-processing's network event stream.

That is how DV software and iniVation cameras publish events (dv-processing `NetworkWriter`,
a TCP server). The stream is the AEDAT4 file layout without the magic line: an int32 size and
the IO header FlatBuffer, then packets (int32 stream id, int32 size, payload), decoded by the
same bounds-checked functions as files (e3dpsm/data/formats/inivation.py):

    with open_live_source("dv://127.0.0.1:7777") as source:
        for chunk in source:            # EventStream chunks, in time order
            ...
        print(source.stopped_reason)

Nothing here can block forever: the connection, the header and every read have a deadline
(`timeout_s`). dv-processing's own `NetworkReader`, used before, has none: a server that
accepts the connection and sends nothing kept its constructor waiting in C++ holding the GIL,
so no Python timeout could end it. When the publisher stops, or sends no events for
`timeout_s`, iteration ENDS (no exception) and `.stopped_reason` says why, e.g. "publisher
dv://127.0.0.1:7777 closed the stream after 123456 events". A URL that is not
`dv://host:port`, a port nobody listens on, a server that sends no stream header within
`timeout_s` or a damaged packet raises `DataError` with one line. Timestamps are the
publisher's (int64 microseconds; DV cameras send epoch time).

Publishing a recording (tests, demos): `publish_recording(path, port)` starts a child process
(`python -m e3dpsm.data.live publish FILE --port P [--speed S]`) that replays any file
`read_events` reads, through dv-processing's own `NetworkWriter`, once a client has connected.
A child process, not a thread, because dv-processing 2.0.4's NetworkWriter destructor
deadlocks while a client is still connected (it calls back into Python holding the GIL):
the publisher process ends with `os._exit` once its queue is drained, and the operating
system closes the socket after the data went out.
"""
from __future__ import annotations

import argparse
import os
import re
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

import numpy as np

from e3dpsm.data.formats import require
from e3dpsm.data.formats.inivation import PACKET_HEADER, columns, decode_event_packet, parse_io_header
from e3dpsm.data.sequence import EventStream
from e3dpsm.errors import DataError

URL_PATTERN = re.compile(r"^dv://(?P<host>\[[0-9a-fA-F:]+\]|[A-Za-z0-9._-]+):(?P<port>\d{1,5})/?$")
MAX_HEADER_BYTES = 1 << 20  # the IO header is an XML stream description of a few kB
MAX_PACKET_BYTES = 64 << 20  # a DV packet holds milliseconds of events: far less
PACKET_US = 5_000  # recording time per published packet at real-time pace
READY_LINE = "e3dpsm-publisher listening"


def is_live_url(source: str) -> bool:
    return str(source).startswith("dv://")


def parse_dv_url(url: str) -> tuple[str, int]:
    match = URL_PATTERN.match(url)
    port = int(match["port"]) if match else 0
    if not match or not 0 < port < 65536:
        raise DataError(f"malformed live source {url!r}: expected dv://HOST:PORT, e.g. dv://127.0.0.1:7777")
    return match["host"].strip("[]"), port


class _Stalled(Exception):
    """Nothing arrived before the deadline."""


class _Closed(Exception):
    """The publisher closed the connection; `partial` bytes of the item being read had come."""

    def __init__(self, partial: int) -> None:
        super().__init__(partial)
        self.partial = partial


class LiveEventSource:
    """An open dv:// network event stream (see the module docstring)."""

    def __init__(self, url: str, timeout_s: float = 5.0) -> None:
        self.url, self.timeout_s = url, float(timeout_s)
        self.events, self.received = 0, 0  # events yielded, bytes read
        self.stopped_reason: str | None = None
        host, port = parse_dv_url(url)
        deadline = time.monotonic() + self.timeout_s
        try:
            self._sock: socket.socket | None = socket.create_connection((host, port), timeout=self.timeout_s)
        except OSError as exc:
            raise DataError(f"cannot connect to {url}: {exc.strerror or exc or type(exc).__name__}") from exc
        try:
            self._read_header(deadline)
        except BaseException:
            self.close()
            raise

    def _read_header(self, deadline: float) -> None:
        try:
            (size,) = struct.unpack("<i", self._read(4, deadline))
            if not 0 < size <= MAX_HEADER_BYTES:
                raise DataError(f"{self.url}: the stream header declares {size} bytes; not a dv-processing event "
                                f"stream (expected 1 to {MAX_HEADER_BYTES})")
            header = parse_io_header(self._read(size, deadline), self.url, 4)
        except _Stalled:
            raise DataError(f"{self.url}: connected, but no stream header came within {self.timeout_s:g} s; is a "
                            "dv-processing publisher (DV software, a camera) listening there?") from None
        except _Closed:
            raise DataError(f"{self.url}: the publisher closed the connection before its stream header") from None
        if header.sensor_hw is None:
            raise DataError(f"{self.url}: the event stream states no sensor size (sizeX, sizeY)")
        self.header, self.sensor_hw = header, header.sensor_hw

    def _read(self, n: int, deadline: float) -> bytearray:
        """Exactly `n` bytes, or _Stalled at the deadline, or _Closed (each recv gets >= 1 byte
        or ends the loop, so it ends by the deadline)."""
        buf, got = bytearray(n), 0
        while got < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self._sock is None:
                raise _Stalled() if self._sock is not None else _Closed(got)
            try:
                self._sock.settimeout(remaining)
                count = self._sock.recv_into(memoryview(buf)[got:], n - got)
            except socket.timeout:
                raise _Stalled() from None
            except OSError:  # closed under us (close() from another thread) or reset by the peer
                count = 0
            if count == 0:
                raise _Closed(got)
            got += count
            self.received += count
        return buf

    def __iter__(self) -> Iterator[EventStream]:
        while self._sock is not None:
            try:
                events = self._next_events(time.monotonic() + self.timeout_s)
            except _Stalled:
                self.stopped_reason = (f"no events from {self.url} for {self.timeout_s:g} s "
                                       f"(after {self.events} events); stopped waiting")
                return
            except _Closed as closed:
                mid = f" ({closed.partial} bytes into a packet, dropped)" if closed.partial else ""
                self.stopped_reason = f"publisher {self.url} closed the stream{mid} after {self.events} events"
                return
            yield self._chunk(events)

    def _next_events(self, deadline: float) -> np.ndarray:
        """The next packet of the event stream holding events; other packets are skipped."""
        while True:
            at = self.received
            stream, size = PACKET_HEADER.unpack(self._read(PACKET_HEADER.size, deadline))
            if stream < 0 or not 0 < size <= MAX_PACKET_BYTES:
                raise DataError(f"{self.url}: corrupted stream at byte {at}: a packet header declares stream {stream} "
                                f"and {size} bytes (at most {MAX_PACKET_BYTES})")
            payload = self._read(size, deadline)
            if stream != self.header.event_stream:
                continue
            try:
                events = decode_event_packet(payload, self.header.compression)
            except ValueError as exc:
                raise DataError(f"{self.url}: corrupted packet at stream byte {at}: {exc}") from exc
            if len(events):
                return events

    def _chunk(self, events: np.ndarray) -> EventStream:
        self.events += len(events)
        c = columns([events])
        return EventStream(x=c["x"], y=c["y"], t_us=c["t"], p=c["p"], sensor_hw=self.sensor_hw)

    def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def __enter__(self) -> LiveEventSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_live_source(url: str, timeout_s: float = 5.0) -> LiveEventSource:
    """Connect to a `dv://host:port` event stream (see the module docstring)."""
    return LiveEventSource(url, timeout_s)


# -- publisher ----------------------------------------------------------------------------------

class RecordingPublisher:
    """A child process replaying a recording on `dv://host:port`; a context manager."""

    def __init__(self, path: str | os.PathLike, port: int, speed: float = 1.0, host: str = "127.0.0.1",
                 wait_client_s: float = 30.0) -> None:
        self.url = f"dv://{host}:{port}"
        cmd = [sys.executable, "-m", "e3dpsm.data.live", "publish", str(path), "--port", str(port),
               "--host", host, "--speed", str(speed), "--wait-client-s", str(wait_client_s)]
        self._process = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self._process.stdout.readline()  # the child says when its server listens
        if not line.startswith(READY_LINE):
            err = self._process.communicate(timeout=30)[1].strip().splitlines()
            raise DataError(f"cannot publish {path} on {self.url}: {err[-1] if err else 'publisher exited'}")

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the replay to end; its exit status (0: every event was sent)."""
        return self._process.wait(timeout)

    def close(self) -> None:
        if self._process.poll() is None:
            self._process.kill()
        self._process.communicate()

    def __enter__(self) -> RecordingPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def publish_recording(path: str | os.PathLike, port: int, speed: float = 1.0, host: str = "127.0.0.1",
                      wait_client_s: float = 30.0) -> RecordingPublisher:
    """Replay `path` on dv://host:port at `speed` x real time (0: as fast as possible), once a
    client connects; returns when the server listens. The replay runs in a child process."""
    return RecordingPublisher(path, port, speed, host, wait_client_s)


def _publish_here(path: Path, port: int, speed: float, host: str, wait_client_s: float) -> None:
    """The child process's work; never returns (os._exit, see the module docstring)."""
    from e3dpsm.data.readers import read_events

    stream = read_events(path)
    dv = require("dv_processing", "publishing a recording")
    height, width = stream.sensor_hw
    writer = dv.io.NetworkWriter(host, port, dv.io.Stream.EventStream(0, "events", "e3dpsm", (width, height)))
    print(READY_LINE, flush=True)
    deadline = time.monotonic() + wait_client_s
    for _ in range(2):  # twice: a client that only probed the port may leave again
        while writer.getClientCount() == 0:
            if time.monotonic() > deadline:
                print(f"no client connected to dv://{host}:{port} within {wait_client_s:g} s", file=sys.stderr)
                os._exit(3)
            time.sleep(0.01)
        time.sleep(0.2)  # a probe leaves, a reader has its stream header
    t_us = stream.t_us
    bounds = _packet_bounds(t_us, PACKET_US if speed > 0 else None)
    start_wall = time.monotonic()
    for lo, hi in bounds:
        if speed > 0:
            due = start_wall + (int(t_us[hi - 1]) - int(t_us[0])) / 1e6 / speed
            time.sleep(max(0.0, due - time.monotonic()))
        store = dv.EventStore()
        for t, x, y, p in zip(t_us[lo:hi].tolist(), stream.x[lo:hi].tolist(), stream.y[lo:hi].tolist(),
                              stream.p[lo:hi].tolist()):
            store.push_back(t, x, y, bool(p))
        writer.writeEvents(store)
    while writer.getQueuedPacketCount() and writer.getClientCount():
        time.sleep(0.01)
    time.sleep(0.2)
    print(f"published {len(stream)} events", flush=True)
    os._exit(0)


def _packet_bounds(t_us: np.ndarray, packet_us: int | None) -> list[tuple[int, int]]:
    """[lo, hi) event ranges: PACKET_US of recording time each, or 50k events when unpaced."""
    n = len(t_us)
    if n == 0:
        return []
    if packet_us is None:
        edges = np.arange(0, n, 50_000)
    else:
        slots = (t_us - t_us[0]) // packet_us
        edges = np.flatnonzero(np.r_[True, slots[1:] != slots[:-1]])
    ends = np.r_[edges[1:], n]
    return list(zip(edges.tolist(), ends.tolist()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m e3dpsm.data.live",
                                     description="Replay an event recording as a dv-processing network stream.")
    sub = parser.add_subparsers(dest="command", required=True)
    pub = sub.add_parser("publish", help="serve FILE on dv://HOST:PORT once a client connects")
    pub.add_argument("file", help="any file e3dpsm reads: .h5/.hdf5/.npz/.aedat4/.raw/.dat")
    pub.add_argument("--port", type=int, required=True)
    pub.add_argument("--host", default="127.0.0.1")
    pub.add_argument("--speed", type=float, default=1.0, help="x real time; 0 sends as fast as possible")
    pub.add_argument("--wait-client-s", type=float, default=30.0, help="give up when no client comes (s)")
    args = parser.parse_args(argv)
    try:
        _publish_here(Path(args.file), args.port, args.speed, args.host, args.wait_client_s)
    except (DataError, RuntimeError) as exc:
        print(f"error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0  # not reached: _publish_here ends the process


if __name__ == "__main__":
    sys.exit(main())
