"""Live event streams: `dv://host:port`, dv-processing's network event stream.

That is how DV software and iniVation cameras publish events (dv-processing `NetworkWriter`,
a TCP server); `open_live_source` connects a dv-processing `NetworkReader` to it:

    with open_live_source("dv://127.0.0.1:7777") as source:
        for chunk in source:            # EventStream chunks, in time order
            ...
        print(source.stopped_reason)

When the publisher stops, or sends nothing for `timeout_s`, iteration ENDS (no exception)
and `.stopped_reason` says why, e.g. "publisher dv://127.0.0.1:7777 closed the stream after
123456 events". A URL that is not `dv://host:port`, or a port nobody listens on, raises
`DataError` with one line ("cannot connect to dv://127.0.0.1:7777: connection refused").
Timestamps are the publisher's (int64 microseconds; DV cameras send epoch time).

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
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

import numpy as np

from e3dpsm.data.formats import require
from e3dpsm.data.sequence import EventStream
from e3dpsm.errors import DataError

URL_PATTERN = re.compile(r"^dv://(?P<host>\[[0-9a-fA-F:]+\]|[A-Za-z0-9._-]+):(?P<port>\d{1,5})/?$")
POLL_S = 0.001  # NetworkReader.getNextEventBatch does not block: poll this often when idle
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


class LiveEventSource:
    """An open dv-processing network event stream (see the module docstring)."""

    def __init__(self, url: str, timeout_s: float = 5.0) -> None:
        self.url, self.timeout_s = url, float(timeout_s)
        host, port = parse_dv_url(url)
        dv = require("dv_processing", f"the live source {url}")
        # A plain connect first: dv-processing's connect holds the GIL and has no timeout.
        try:
            socket.create_connection((host, port), timeout=self.timeout_s).close()
            self._reader = dv.io.NetworkReader(host, port)
        except (OSError, RuntimeError) as exc:
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise DataError(f"cannot connect to {url}: {reason}") from exc
        if not self._reader.isEventStreamAvailable():
            self.close()
            raise DataError(f"{url} publishes no event stream")
        width, height = self._reader.getEventResolution()
        self.sensor_hw: tuple[int, int] = (int(height), int(width))
        self.events = 0
        self.stopped_reason: str | None = None

    def __iter__(self) -> Iterator[EventStream]:
        idle_since = time.monotonic()
        while self._reader is not None:
            batch = self._reader.getNextEventBatch()
            if batch is not None and batch.size():
                idle_since = time.monotonic()
                yield self._chunk(batch.numpy())
                continue
            if not self._reader.isRunning():
                # the connection is gone; what it delivered before closing is still buffered
                while (batch := self._reader.getNextEventBatch()) is not None:
                    if batch.size():
                        yield self._chunk(batch.numpy())
                self.stopped_reason = f"publisher {self.url} closed the stream after {self.events} events"
                return
            if time.monotonic() - idle_since > self.timeout_s:
                self.stopped_reason = (f"no events from {self.url} for {self.timeout_s:g} s "
                                       f"(after {self.events} events); stopped waiting")
                return
            time.sleep(POLL_S)

    def _chunk(self, events: np.ndarray) -> EventStream:
        self.events += len(events)
        return EventStream(
            x=events["x"].astype(np.int32), y=events["y"].astype(np.int32),
            t_us=events["timestamp"].astype(np.int64), p=events["polarity"].astype(np.uint8),
            sensor_hw=self.sensor_hw,
        )

    def close(self) -> None:
        self._reader = None  # the reader's destructor closes the connection

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
    for _ in range(2):  # twice: the first client may be LiveEventSource's reachability probe
        while writer.getClientCount() == 0:
            if time.monotonic() > deadline:
                print(f"no client connected to dv://{host}:{port} within {wait_client_s:g} s", file=sys.stderr)
                os._exit(3)
            time.sleep(0.01)
        time.sleep(0.2)  # the probe leaves, the reader finishes its handshake
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
