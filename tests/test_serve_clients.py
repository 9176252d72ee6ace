"""The viewer's per-client queues and the hub (e3dpsm/serve/clients.py) on their own, with a
fake clock: what each queue keeps and drops, the order a sender gets messages in, the counters
and summaries the report lists, and the hub's bounded memory of closed clients. The bounds are
written here from docs/serve.md (the latest 100 closed clients listed) and the module's
contract (64 control messages waiting), not read from the module."""
from __future__ import annotations

import asyncio
import json

import pytest

from e3dpsm.serve import clients
from e3dpsm.serve.clients import ClientChannel, ClientHub
from e3dpsm.serve.protocol import LatencyReport, PoseMessage

CONTROL_KEPT = 64
CLOSED_LISTED = 100  # docs/serve.md: "per the latest 100 closed"
NOW_S = 1_000.0  # the fake clock, seconds
EMPTY = {"count": 0, "p50": None, "p90": None, "p99": None, "max": None}


@pytest.fixture(autouse=True)
def clock(monkeypatch):
    now = [NOW_S]
    monkeypatch.setattr(clients.time, "time", lambda: now[0])
    return now


def _pose(seq: int, window_end_ms: float = NOW_S * 1e3 - 5.0) -> PoseMessage:
    return PoseMessage(seq=seq, t_us=seq * 10_000, window_end_wall_ms=window_end_ms, text=f"pose {seq}")


def _drain(channel: ClientChannel) -> list[tuple[str, str]]:
    """Every message ready now, in the order the sender gets them."""
    async def take() -> list[tuple[str, str]]:
        taken = []
        while channel.has_control or channel.backlog or channel._frame is not None:
            kind, text, _ = await channel.next_message()
            taken.append((kind, text))
        return taken
    return asyncio.run(take())


def test_a_new_channel_summarises_to_zeros() -> None:
    channel = ClientChannel(7, "127.0.0.1:5000", pose_backlog=3)
    assert channel.open and channel.backlog == 0 and not channel.has_control
    assert channel.summary() == {
        "client_id": 7, "remote": "127.0.0.1:5000", "agent": "", "connected_wall_ms": NOW_S * 1e3,
        "closed_wall_ms": None, "close_code": None, "close_reason": None, "poses_sent": 0, "poses_dropped": 0,
        "last_seq_sent": -1, "pose_backlog_at_end": 0, "frames_sent": 0, "frames_dropped": 0, "control_dropped": 0,
        "sent_latency_ms": EMPTY, "page_latency_ms": EMPTY, "page": None}


def test_control_keeps_the_latest_64_in_order() -> None:
    channel = ClientChannel(0, "r", pose_backlog=3)
    for i in range(CONTROL_KEPT + 6):
        channel.put_control(f"c{i}")
    assert channel.control_dropped == 6
    assert _drain(channel) == [("control", f"c{i}") for i in range(6, CONTROL_KEPT + 6)]
    channel.put_control("one more")  # an emptied queue takes messages again without dropping
    assert channel.control_dropped == 6 and _drain(channel) == [("control", "one more")]


def test_exactly_64_control_messages_drop_none() -> None:
    channel = ClientChannel(0, "r", pose_backlog=3)
    for i in range(CONTROL_KEPT):
        channel.put_control(f"c{i}")
    assert channel.control_dropped == 0 and len(_drain(channel)) == CONTROL_KEPT


@pytest.mark.parametrize("backlog, put, kept", [(3, 3, [0, 1, 2]), (3, 5, [2, 3, 4]), (1, 4, [3])])
def test_poses_drop_their_oldest_beyond_the_backlog(backlog, put, kept) -> None:
    channel = ClientChannel(0, "r", pose_backlog=backlog)
    for seq in range(put):
        channel.put_pose(_pose(seq))
    assert channel.backlog == len(kept) and channel.poses_dropped == put - len(kept)
    assert _drain(channel) == [("pose", f"pose {seq}") for seq in kept]
    assert channel.backlog == 0


def test_a_new_frame_replaces_one_not_yet_sent() -> None:
    channel = ClientChannel(0, "r", pose_backlog=3)
    channel.put_frame("f0")
    assert channel.frames_dropped == 0
    channel.put_frame("f1")
    channel.put_frame("f2")
    assert channel.frames_dropped == 2
    assert _drain(channel) == [("frame", "f2")]
    channel.put_frame("f3")  # the slot is empty again: nothing dropped
    assert channel.frames_dropped == 2 and _drain(channel) == [("frame", "f3")]


def test_control_then_poses_then_the_frame() -> None:
    channel = ClientChannel(0, "r", pose_backlog=5)
    channel.put_frame("f")
    channel.put_pose(_pose(1))
    channel.put_control("c1")
    channel.put_pose(_pose(2))
    channel.put_control("c2")
    assert _drain(channel) == [("control", "c1"), ("control", "c2"), ("pose", "pose 1"), ("pose", "pose 2"),
                               ("frame", "f")]


def test_a_sender_waits_until_something_is_put() -> None:
    async def scenario() -> list:
        channel = ClientChannel(0, "r", pose_backlog=3)
        got = []
        for put in (lambda: channel.put_pose(_pose(4)), lambda: channel.put_control("c"),
                    lambda: channel.put_frame("f")):
            waiting = asyncio.ensure_future(channel.next_message())
            await asyncio.sleep(0.01)
            assert not waiting.done()  # nothing queued: it waits, and a wake from before does not free it
            put()
            got.append(await asyncio.wait_for(waiting, 1.0))
        return got
    got = asyncio.run(scenario())
    assert [(kind, text) for kind, text, _ in got] == [("pose", "pose 4"), ("control", "c"), ("frame", "f")]
    assert got[0][2] == _pose(4) and got[1][2] is None and got[2][2] is None


def test_sent_counts_what_was_written(clock) -> None:
    channel = ClientChannel(0, "r", pose_backlog=3)
    channel.sent("pose", _pose(9, window_end_ms=NOW_S * 1e3 - 20.0))
    clock[0] += 0.030  # 30 ms later
    channel.sent("pose", _pose(12, window_end_ms=NOW_S * 1e3))
    channel.sent("frame", None)
    channel.sent("frame", None)
    channel.sent("control", None)
    channel.sent("pose", None)  # a pose kind without its message counts nothing
    summary = channel.summary()
    assert (summary["poses_sent"], summary["last_seq_sent"], summary["frames_sent"]) == (2, 12, 2)
    latency = summary["sent_latency_ms"]
    assert latency["count"] == 2 and latency["max"] == pytest.approx(30.0)
    assert channel.sent_latency_ms.min == pytest.approx(20.0)


def test_a_page_report_is_kept_and_its_samples_merged() -> None:
    channel = ClientChannel(0, "r", pose_backlog=3)
    channel.page_reported(LatencyReport(samples_ms=(10.0, 30.0), received=5, drawn=4, gaps=1, out_of_order=0))
    channel.page_reported(LatencyReport(samples_ms=(50.0,), received=9, drawn=8, gaps=2, out_of_order=1))
    summary = channel.summary()
    assert summary["page"] == {"received": 9, "drawn": 8, "gaps": 2, "out_of_order": 1}
    assert summary["page_latency_ms"]["count"] == 3 and summary["page_latency_ms"]["max"] == 50.0
    assert channel.page_latency_ms.min == 10.0


def test_closing_is_recorded_once(clock) -> None:
    channel = ClientChannel(0, "r", pose_backlog=3)
    clock[0] += 2.5
    channel.closed(1001, "going away")
    clock[0] += 1.0
    channel.closed(1006, "later")
    assert channel.open is False
    summary = channel.summary()
    assert (summary["closed_wall_ms"], summary["close_code"], summary["close_reason"]) == (
        (NOW_S + 2.5) * 1e3, 1001, "going away")


def test_a_close_without_a_code_is_recorded() -> None:
    channel = ClientChannel(0, "r", pose_backlog=3)
    channel.closed(None, None)
    assert not channel.open and channel.closed_wall_ms == NOW_S * 1e3
    assert (channel.close_code, channel.close_reason) == (None, None)


def test_times_are_rounded_to_a_tenth_of_a_millisecond(clock) -> None:
    clock[0] = 1234.56789
    channel = ClientChannel(0, "r", pose_backlog=3)
    clock[0] = 1240.12347
    channel.closed(1000, "")
    summary = channel.summary()
    assert (summary["connected_wall_ms"], summary["closed_wall_ms"]) == (1234567.9, 1240123.5)


def test_the_hub_numbers_clients_and_signals_each() -> None:
    hub = ClientHub(pose_backlog=4)
    assert not hub.connected.is_set() and hub.seen == 0 and hub.status is None
    first, second = hub.add("a"), hub.add("b")
    assert (first.client_id, second.client_id, hub.seen) == (0, 1, 2)
    assert first.pose_backlog == 4 and hub.connected.is_set()
    assert hub.open == {0: first, 1: second} and hub.count_open() == 2


def test_broadcasts_reach_open_clients_only() -> None:
    hub = ClientHub(pose_backlog=4)
    a, b = hub.add("a"), hub.add("b")
    b.closed(1000, "")  # closed, not yet retired: still in the hub, no longer sent to
    hub.broadcast_pose(_pose(1))
    hub.broadcast_frame("f")
    hub.set_status("s")
    assert hub.status == "s" and hub.open_clients() == [a] and hub.count_open() == 1
    assert _drain(a) == [("control", "s"), ("pose", "pose 1"), ("frame", "f")]
    assert _drain(b) == []


def test_stats_carry_each_clients_own_counters() -> None:
    hub = ClientHub(pose_backlog=1)
    a, b = hub.add("a"), hub.add("b")
    a.put_pose(_pose(1))
    a.put_pose(_pose(2))  # drops one
    b.put_frame("f1")
    b.put_frame("f2")  # drops one
    hub.broadcast_stats(step_ms=3.5)
    stats_a = json.loads([t for k, t in _drain(a) if k == "control"][0])
    stats_b = json.loads([t for k, t in _drain(b) if k == "control"][0])
    assert stats_a == {"type": "stats", "step_ms": 3.5, "client_id": 0, "poses_dropped": 1, "frames_dropped": 0,
                       "backlog": 1}
    assert stats_b == {"type": "stats", "step_ms": 3.5, "client_id": 1, "poses_dropped": 0, "frames_dropped": 1,
                       "backlog": 0}


def test_retiring_keeps_the_summary_and_the_latencies_once() -> None:
    hub = ClientHub(pose_backlog=4)
    a, b = hub.add("a"), hub.add("b")
    a.sent("pose", _pose(1, window_end_ms=NOW_S * 1e3 - 8.0))
    a.page_reported(LatencyReport(samples_ms=(40.0,), received=1, drawn=1, gaps=0, out_of_order=0))
    b.sent("pose", _pose(1, window_end_ms=NOW_S * 1e3 - 2.0))
    a.closed(1000, "bye")
    hub.retire(a)
    hub.retire(a)  # a second retire of the same client changes nothing
    assert hub.retired == 1 and hub.open == {1: b}
    assert [s["client_id"] for s in hub.summaries()] == [0, 1]
    assert hub.summaries()[0] == a.summary()
    sent, page = hub.latency_ms("sent"), hub.latency_ms("page")
    assert (sent.count, sent.min, sent.max) == (2, pytest.approx(2.0), pytest.approx(8.0))
    assert (page.count, page.max) == (1, 40.0)
    assert hub.closed_latency_ms["sent"].count == 1 and hub.closed_latency_ms["page"].count == 1


def test_the_hub_lists_the_latest_100_closed_clients() -> None:
    hub = ClientHub(pose_backlog=2)
    channels = [hub.add(f"r{i}") for i in range(CLOSED_LISTED + 5)]
    for channel in channels:
        channel.sent("pose", _pose(channel.client_id))
        channel.closed(1000, "")
        hub.retire(channel)
    still_open = hub.add("last")
    listed = [s["client_id"] for s in hub.summaries()]
    assert listed == [*range(5, CLOSED_LISTED + 5), still_open.client_id]
    assert hub.retired == CLOSED_LISTED + 5 and hub.seen == CLOSED_LISTED + 6
    assert hub.latency_ms("sent").count == CLOSED_LISTED + 5  # every retired client's latencies, listed or not


def test_summaries_are_ordered_by_client_id() -> None:
    hub = ClientHub(pose_backlog=2)
    hub.add("a"), hub.add("b")
    c = hub.add("c")
    c.closed(1000, "")
    hub.retire(c)  # retired before the older ones: listed in id order all the same
    assert [s["client_id"] for s in hub.summaries()] == [0, 1, 2]
    assert [s["remote"] for s in hub.summaries()] == ["a", "b", "c"]
