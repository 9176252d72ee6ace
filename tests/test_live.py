"""Live dv:// source on localhost: dv-processing's own NetworkWriter (in a publisher process)
replays a recording; the reader gets the same events, and `run` the same poses."""
from __future__ import annotations

import json
import socket

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
