"""Per-client send queues: the estimator hands every message to every client without ever
waiting on one, and each client's own sender task writes them out as fast as that client reads.

Per client: control messages (hello, status, stats, pong) in a small FIFO; poses in a bounded
FIFO that drops its OLDEST pose when full (counted; order is never changed, so the client sees
increasing seq with a gap); and one frame slot, where a new frame replaces a frame not yet sent
(counted: frames are only worth showing fresh). A client that stops reading blocks only its own
sender in `send_str` (aiohttp waits for the socket to drain), while its queue stays bounded.

Memory stays bounded however long the server runs and however many clients come and go:
latencies are kept as fixed-size histograms, and a closed client leaves the hub, its summary
kept among the latest MAX_LISTED_CLOSED and its latencies merged into the hub's.
"""
from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from e3dpsm.serve import protocol
from e3dpsm.serve.protocol import LatencyReport, PoseMessage
from e3dpsm.utils.stats import LogHistogram

MAX_CONTROL = 64  # hello + status + stats + pongs waiting; older ones are dropped beyond it
MAX_LISTED_CLOSED = 100  # closed clients the report lists one by one (the latest); the rest are counted


@dataclass
class ClientChannel:
    client_id: int
    remote: str
    pose_backlog: int
    connected_wall_ms: float = field(default_factory=lambda: time.time() * 1e3)
    agent: str = ""
    poses_sent: int = 0
    poses_dropped: int = 0
    frames_sent: int = 0
    frames_dropped: int = 0
    control_dropped: int = 0
    last_seq_sent: int = -1
    sent_latency_ms: LogHistogram = field(default_factory=LogHistogram)  # window end -> written to the socket
    page_latency_ms: LogHistogram = field(default_factory=LogHistogram)  # window end -> drawn, as the page reports
    page_report: LatencyReport | None = None
    closed_wall_ms: float | None = None
    close_code: int | None = None
    close_reason: str | None = None

    def __post_init__(self) -> None:
        self._control: deque[str] = deque()
        self._poses: deque[PoseMessage] = deque()
        self._frame: str | None = None
        self._wake = asyncio.Event()
        self.open = True

    # ---- producer side (the estimator loop; never blocks) ----
    def put_control(self, text: str) -> None:
        if len(self._control) >= MAX_CONTROL:
            self._control.popleft()
            self.control_dropped += 1
        self._control.append(text)
        self._wake.set()

    def put_pose(self, message: PoseMessage) -> None:
        if len(self._poses) >= self.pose_backlog:
            self._poses.popleft()
            self.poses_dropped += 1
        self._poses.append(message)
        self._wake.set()

    def put_frame(self, text: str) -> None:
        if self._frame is not None:
            self.frames_dropped += 1
        self._frame = text
        self._wake.set()

    @property
    def backlog(self) -> int:
        return len(self._poses)

    @property
    def has_control(self) -> bool:
        return bool(self._control)

    # ---- consumer side (this client's sender task) ----
    async def next_message(self) -> tuple[str, str, PoseMessage | None]:
        """(kind, text, pose): control first, then poses in order, then the latest frame."""
        while True:
            if self._control:
                return "control", self._control.popleft(), None
            if self._poses:
                message = self._poses.popleft()
                return "pose", message.text, message
            if self._frame is not None:
                text, self._frame = self._frame, None
                return "frame", text, None
            self._wake.clear()
            await self._wake.wait()

    def sent(self, kind: str, pose: PoseMessage | None) -> None:
        if kind == "pose" and pose is not None:
            self.poses_sent += 1
            self.last_seq_sent = pose.seq
            self.sent_latency_ms.add(time.time() * 1e3 - pose.window_end_wall_ms)
        elif kind == "frame":
            self.frames_sent += 1

    def page_reported(self, report: LatencyReport) -> None:
        self.page_latency_ms.extend(report.samples_ms)
        self.page_report = report

    def closed(self, code: int | None, reason: str | None) -> None:
        if self.closed_wall_ms is None:
            self.open = False
            self.closed_wall_ms = time.time() * 1e3
            self.close_code, self.close_reason = code, reason

    def summary(self) -> dict[str, Any]:
        page = self.page_report
        return {
            "client_id": self.client_id, "remote": self.remote, "agent": self.agent,
            "connected_wall_ms": round(self.connected_wall_ms, 1),
            "closed_wall_ms": None if self.closed_wall_ms is None else round(self.closed_wall_ms, 1),
            "close_code": self.close_code, "close_reason": self.close_reason,
            "poses_sent": self.poses_sent, "poses_dropped": self.poses_dropped, "last_seq_sent": self.last_seq_sent,
            "pose_backlog_at_end": self.backlog, "frames_sent": self.frames_sent,
            "frames_dropped": self.frames_dropped, "control_dropped": self.control_dropped,
            "sent_latency_ms": self.sent_latency_ms.summary(),
            "page_latency_ms": self.page_latency_ms.summary(),
            "page": None if page is None else {"received": page.received, "drawn": page.drawn, "gaps": page.gaps,
                                               "out_of_order": page.out_of_order},
        }


class ClientHub:
    """The open clients get each broadcast; every client seen is counted, and summarised in the report."""

    def __init__(self, pose_backlog: int) -> None:
        self.pose_backlog = pose_backlog
        self.open: dict[int, ClientChannel] = {}
        self.seen = 0
        self.retired = 0  # closed clients that left the hub
        self.closed_summaries: deque[dict[str, Any]] = deque(maxlen=MAX_LISTED_CLOSED)
        self.closed_latency_ms = {"sent": LogHistogram(), "page": LogHistogram()}  # of the retired clients
        self.connected = asyncio.Event()  # set on each new client (for --wait-clients)
        self.status: str | None = None  # the latest status message, sent to clients joining later

    def add(self, remote: str) -> ClientChannel:
        channel = ClientChannel(self.seen, remote, self.pose_backlog)
        self.seen += 1
        self.open[channel.client_id] = channel
        self.connected.set()
        return channel

    def retire(self, channel: ClientChannel) -> None:
        """A closed client leaves: its summary is kept (the latest MAX_LISTED_CLOSED), its latencies merged."""
        if self.open.pop(channel.client_id, None) is None:
            return
        self.retired += 1
        self.closed_summaries.append(channel.summary())
        self.closed_latency_ms["sent"].merge(channel.sent_latency_ms)
        self.closed_latency_ms["page"].merge(channel.page_latency_ms)

    def open_clients(self) -> list[ClientChannel]:
        return [c for c in self.open.values() if c.open]

    def count_open(self) -> int:
        return len(self.open_clients())

    def summaries(self) -> list[dict[str, Any]]:
        """Every client still in the hub and the latest retired ones, by id."""
        listed = [*self.closed_summaries, *(c.summary() for c in self.open.values())]
        return sorted(listed, key=lambda summary: summary["client_id"])

    def latency_ms(self, kind: str) -> LogHistogram:
        """"sent" or "page" latencies of every client seen, merged."""
        merged = LogHistogram()
        merged.merge(self.closed_latency_ms[kind])
        for channel in self.open.values():
            merged.merge(channel.sent_latency_ms if kind == "sent" else channel.page_latency_ms)
        return merged

    def broadcast_pose(self, message: PoseMessage) -> None:
        for channel in self.open_clients():
            channel.put_pose(message)

    def broadcast_frame(self, text: str) -> None:
        for channel in self.open_clients():
            channel.put_frame(text)

    def broadcast_control(self, text: str) -> None:
        for channel in self.open_clients():
            channel.put_control(text)

    def set_status(self, text: str) -> None:
        self.status = text
        self.broadcast_control(text)

    def broadcast_stats(self, **fields: Any) -> None:
        """Stats with each client's own counters (its drops, its backlog)."""
        for channel in self.open_clients():
            channel.put_control(protocol.stats(
                **fields, client_id=channel.client_id, poses_dropped=channel.poses_dropped,
                frames_dropped=channel.frames_dropped, backlog=channel.backlog))
