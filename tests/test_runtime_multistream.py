"""Runtime sessions without state copies (IOBindingStepSession) and many streams through one
session (MultiStreamEstimator, `e3dpsm run --events a b c`): the same poses as the plain
numpy StepSession and as independent StreamingPoseEstimator runs."""
from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest

from e3dpsm.cli import main
from e3dpsm.runtime.run_many import stream_names
from e3dpsm.data.readers import write_events_h5
from e3dpsm.data.sequence import EventStream
from e3dpsm.errors import ConfigError, InputError
from e3dpsm.runtime import IOBindingStepSession, MultiStreamEstimator, StepSession, StreamingPoseEstimator
from _runtime_helpers import WINDOW_US, chunked, exported_tiny, reference_frames, shared_session, step_frames, synthetic_stream

BATCHED_TOL_MM = 1e-4  # batch of N vs N batches of one: the kernels may sum in another order
CSV_TOL_MM = 1e-4  # 4 decimals in the CSV


@pytest.fixture(scope="session")
def tiny_graph(tmp_path_factory) -> tuple[object, Path]:
    return exported_tiny(str(tmp_path_factory.getbasetemp()))


@pytest.fixture(scope="session")
def session(tiny_graph) -> StepSession:
    return shared_session(str(tiny_graph[1]))


@pytest.fixture(scope="module")
def bound(tiny_graph) -> IOBindingStepSession:
    return IOBindingStepSession(tiny_graph[1], threads=1)


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    """Frames of a stream with a silent gap (some all-zero), plus one all-zero frame."""
    _, _, lnes = reference_frames(*synthetic_stream(seed=5, windows=12))
    return np.concatenate([lnes, np.zeros((1, *lnes.shape[1:]), np.float32)])


# -- IOBindingStepSession -------------------------------------------------------------------------

def test_iobinding_rollout_is_bitwise_equal_to_numpy_session(session, bound, frames):
    """200 steps, a reset half way, window lengths varying: outputs and states bit for bit."""
    steps, reset_at = 200, 111
    window_ms = [20.0, 20.0, 10.0, 33.0, 20.0]
    numpy_state, bound_state = session.init_state(1), bound.init_state(1)
    for k in range(steps):
        if k == reset_at:
            numpy_state, bound_state = session.init_state(1), bound.init_state(1)
        frame, window = frames[k % len(frames)][None], window_ms[k % len(window_ms)]
        expected, numpy_state = session.step(frame, numpy_state, window)
        got, bound_state = bound.step(frame, bound_state, window)
        for name, value in expected.items():
            np.testing.assert_array_equal(got[name], value, err_msg=f"{name} at step {k}")
        if k % 40 == 0 or k == steps - 1:  # reading a state back does not disturb the rollout
            for name, value in numpy_state.items():
                np.testing.assert_array_equal(bound_state[name], value, err_msg=f"state {name} at step {k}")
    held = IOBindingStepSession(bound.path, threads=1)  # the stateful API: a few steps, reset, then as above
    for k in range(10):
        held.advance(frames[k][None], 20.0)
    held.reset(1)
    for k in range(reset_at, steps):
        outputs = held.advance(frames[k % len(frames)][None], window_ms[k % len(window_ms)])
    np.testing.assert_array_equal(outputs["pose"], expected["pose"])
    for name, value in numpy_state.items():
        np.testing.assert_array_equal(held.states()[name], value)
    assert numpy_state["s5_stage1_re"].any()  # the state moved away from its zero start


def test_iobinding_batch_with_per_row_windows(session, bound, frames):
    batch = frames[:3]
    windows = np.array([20.0, 10.0, 40.0], np.float32)
    expected, numpy_state = session.step(batch, session.init_state(3), windows)
    got, state = bound.step(batch, bound.init_state(3), windows)
    expected, numpy_state = session.step(batch[::-1].copy(), numpy_state, windows)
    got, state = bound.step(batch[::-1].copy(), state, windows)
    for name, value in expected.items():
        np.testing.assert_array_equal(got[name], value)
    for name, value in numpy_state.items():
        np.testing.assert_array_equal(state[name], value)


def test_iobinding_overwritten_state_raises(bound, frames):
    """A chain of states reuses two buffers: state k - 1 is gone once step k + 1 ran; it must say so.
    A chain started from numpy states gets buffers of its own."""
    frame = frames[:1]
    _, s1 = bound.step(frame, bound.init_state(1), 20.0)
    _, s2 = bound.step(frame, s1, 20.0)
    kept = s1.to_numpy()
    assert s1.valid and s2.valid
    _, s3 = bound.step(frame, s2, 20.0)
    assert not s1.valid and s2.valid and s3.valid
    with pytest.raises(InputError, match="overwritten"):
        bound.step(frame, s1, 20.0)
    with pytest.raises(InputError, match="overwritten"):
        s1["s5_stage1_re"]
    expected, _ = bound.step(frame, s2, 20.0)  # s2 -> s3' in s3's buffer: s3 is gone, s2 stays
    assert s2.valid and not s3.valid
    _, other = bound.step(frame, kept, 20.0)  # a numpy copy of s1 starts a chain of its own
    assert s2.valid and other.valid
    for name in other:
        np.testing.assert_array_equal(other[name], s2[name])  # s1 -> s2 again
    again, _ = bound.step(frame, other, 20.0)
    np.testing.assert_array_equal(again["pose"], expected["pose"])


def test_streaming_estimator_runs_on_iobinding_session(session, bound):
    stream = synthetic_stream(seed=8, windows=9)
    cuts = np.random.default_rng(1).integers(0, stream[2].size, 5)
    plain = [p.pose for p in StreamingPoseEstimator(session).run(chunked(stream, cuts))]
    fast = [p.pose for p in StreamingPoseEstimator(bound).run(chunked(stream, cuts))]
    np.testing.assert_array_equal(np.stack(fast), np.stack(plain))


# -- MultiStreamEstimator ---------------------------------------------------------------------------

STREAMS = {
    # id: (seed, windows, window_ms, start offset in us or None, chunk cuts)
    "a": (11, 9, 20.0, None, 4),
    "b": (12, 8, 10.0, 7_000, 6),
    "c": (13, 7, 20.0, None, 6),
    "d": (14, 9, 40.0, None, 5),
    "e": (15, 7, 20.0, -3_000, 4),
}
# Per tick: streams that join, that leave (after `finish` when marked "!"), and that flush.
SCHEDULE = [
    {"join": ["a", "b"]},
    {"join": ["c"]},
    {},
    {"leave": ["c"]},  # leaves mid-stream: rows move, poses so far only
    {"join": ["d"], "flush": ["a"]},
    {"leave": ["a!"]},
    {"join": ["e"]},  # reuses a freed row
    {}, {}, {},
    {"leave": ["b!", "d!", "e!"]},
]


def stream_chunks(sid: str) -> list[tuple[np.ndarray, ...]]:
    seed, windows, _, _, pieces = STREAMS[sid]
    stream = synthetic_stream(seed=seed, windows=windows, t0_us=1_000_000 + 3_333 * seed)
    cuts = np.random.default_rng(seed).integers(0, stream[2].size, pieces - 1)
    return chunked(stream, cuts)


def stream_start(sid: str) -> int | None:
    offset = STREAMS[sid][3]
    return None if offset is None else 1_000_000 + 3_333 * STREAMS[sid][0] + offset


def run_schedule(model) -> tuple[dict[str, list], dict[str, list], MultiStreamEstimator]:
    """(poses of the multi-stream estimator, poses of one StreamingPoseEstimator per stream)."""
    multi = MultiStreamEstimator(model)
    single: dict[str, StreamingPoseEstimator] = {}
    chunks = {sid: stream_chunks(sid) for sid in STREAMS}
    got: dict[str, list] = {sid: [] for sid in STREAMS}
    want: dict[str, list] = {sid: [] for sid in STREAMS}
    last_t: dict[str, int] = {}
    for tick in SCHEDULE:
        for sid in tick.get("join", []):
            window_ms, start = STREAMS[sid][2], stream_start(sid)
            multi.add_stream(sid, start_us=start, window_ms=window_ms)
            single[sid] = StreamingPoseEstimator(model, window_ms=window_ms, start_us=start)
        batch = {sid: chunks[sid].pop(0) for sid in multi.stream_ids if chunks[sid]}
        for sid, poses in multi.push_many(batch).items():
            got[sid] += poses
        for sid, chunk in batch.items():
            want[sid] += single[sid].push(*chunk)
            last_t[sid] = int(chunk[2][-1]) if len(chunk[2]) else last_t.get(sid, 0)
        for sid in tick.get("flush", []):
            until = last_t[sid] + 1
            got[sid] += multi.flush(sid, until)
            want[sid] += single[sid].flush(until)
        for mark in tick.get("leave", []):
            sid = mark.rstrip("!")
            if mark.endswith("!"):
                while chunks[sid]:  # the rest of its events, then the end of the stream
                    chunk = chunks[sid].pop(0)
                    got[sid] += multi.push(sid, *chunk)
                    want[sid] += single[sid].push(*chunk)
                got[sid] += multi.finish(sid)
                want[sid] += single[sid].finish()
            got[sid] += multi.remove_stream(sid)
    return got, want, multi


@pytest.mark.parametrize("kind", ["numpy", "iobinding"])
def test_multistream_equals_independent_streams(kind, session, bound):
    got, want, multi = run_schedule(session if kind == "numpy" else bound)
    for sid in STREAMS:
        assert len(want[sid]) >= 3, sid
        assert [p.t_us for p in got[sid]] == [p.t_us for p in want[sid]], sid
        assert [p.events for p in got[sid]] == [p.events for p in want[sid]], sid
        for k, (g, w) in enumerate(zip(got[sid], want[sid])):
            for name in ("pose", "pose_direct", "pose_delta"):
                np.testing.assert_allclose(g.outputs[name], w.outputs[name], rtol=0, atol=BATCHED_TOL_MM,
                                           err_msg=f"stream {sid} window {k} {name}")
    assert any(p.events == 0 for sid in STREAMS for p in want[sid])  # empty windows were stepped
    assert multi.stream_ids == []
    stats = multi.stats.to_dict()
    assert stats["rows_stepped"] == sum(len(v) for v in want.values())
    assert stats["mean_batch"] > 1.3  # rows really shared session calls


def test_multistream_rejects_bad_use_and_keeps_other_streams(session):
    multi = MultiStreamEstimator(session)
    multi.add_stream("ok")
    multi.add_stream("bad")
    with pytest.raises(InputError, match="already exists"):
        multi.add_stream("ok")
    with pytest.raises(InputError, match="unknown stream"):
        multi.push("nope", *(np.zeros(1, np.int64),) * 4)
    good = synthetic_stream(seed=21, windows=7)
    broken = tuple(np.array(a[:50], dtype=np.float64) for a in synthetic_stream(seed=22, windows=7))
    broken[0][3] = np.nan
    with pytest.raises(InputError, match="stream 'bad'"):
        multi.push_many({"ok": good, "bad": broken})
    assert multi.stats.rows_stepped == 0  # nothing stepped by the failed call
    late = multi.finish("ok")  # the windows "ok" completed in the failed call come now, in order
    reference = StreamingPoseEstimator(session)
    expected = reference.push(*good) + reference.finish()
    assert [p.t_us for p in late] == [p.t_us for p in expected]
    np.testing.assert_allclose(np.stack([p.pose for p in late]), np.stack([p.pose for p in expected]),
                               rtol=0, atol=BATCHED_TOL_MM)


# -- e3dpsm run with several event files ---------------------------------------------------------------

def write_npz(path: Path, x, y, t, p) -> Path:
    np.savez(path, x=x, y=y, t=t, p=p)
    return path


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array(rows[1:], dtype=np.float64)


def test_cli_runs_several_files_into_a_folder(tiny_graph, session, tmp_path, capsys, monkeypatch):
    streams = {name: synthetic_stream(seed=seed, windows=windows)
               for name, seed, windows in (("walk", 31, 8), ("sit", 33, 10))}
    jump = synthetic_stream(seed=32, windows=7, boundary_bursts=True)
    # Ends on a burst 1 us before a window end: only the end-of-stream step emits that window.
    streams["jump"] = tuple(a[jump[2] < jump[2][0] + 6 * WINDOW_US] for a in jump)
    files = [write_npz(tmp_path / f"{name}.npz", *stream) for name, stream in streams.items()]
    out = tmp_path / "poses"
    from e3dpsm.runtime import run_many as run_many_module

    seen_while_running = []
    real_run_streams = run_many_module._run_streams

    def run_streams(*args):  # what the folder holds while the streams run: hidden temporaries only
        seen_while_running.extend(sorted(p.name for p in out.iterdir()))
        return real_run_streams(*args)

    monkeypatch.setattr(run_many_module, "_run_streams", run_streams)
    code = main(["run", "--model", str(tiny_graph[1]), "--events", *map(str, files), "--out", str(out),
                 "--chunk-events", "900", "--threads", "1"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert sorted(p.name for p in out.iterdir()) == ["jump.csv", "run.report.json", "sit.csv", "walk.csv"]
    # Each temporary is hidden and keeps its file's extension, so a crashed run's leftovers say what they were.
    assert len(seen_while_running) == 4 and all(
        re.fullmatch(rf"\.{re.escape(final)}\.[^.]+{re.escape(Path(final).suffix)}", name)
        for final, name in zip(["jump.csv", "run.report.json", "sit.csv", "walk.csv"], seen_while_running)), \
        seen_while_running
    report = json.loads((out / "run.report.json").read_text())
    assert report["command"] == "run" and "versions" in report
    totals = report["totals"]
    assert captured.out.strip().splitlines()[-1] == (
        f"3 streams, {totals['rows_stepped']} poses in {totals['session_calls']} batched steps (mean batch "
        f"{totals['mean_batch']:.2f}) at {totals['mean_step_ms_per_pose']:.2f} ms/pose + "
        f"{totals['mean_overhead_ms_per_pose']:.2f} ms runtime overhead -> {out}")
    assert report["batching"] == "the streams' complete windows share batched session calls (one row per stream)"
    assert report["csv_naming"] == (
        "each CSV is named by the shortest end of its event file's path (folders, stem; joined with '__') that "
        "tells it apart from the other files, after the end they all share")
    for name, stream in streams.items():  # independent reference: windows cut directly, stepped one by one
        starts, counts, frames = reference_frames(*stream)
        expected, _ = step_frames(session, frames)
        header, table = read_csv(out / f"{name}.csv")
        assert header[0] == "t_us" and len(header) == 1 + 16 * 3
        assert table[:, 0].astype(np.int64).tolist() == (starts + WINDOW_US).tolist()
        np.testing.assert_allclose(table[:, 1:].reshape(-1, 16, 3), expected, rtol=0, atol=CSV_TOL_MM)
        entry = report["streams"][name]
        assert entry["windows"] == len(starts) and entry["events"] == int(counts.sum())
        assert entry["csv"] == str(out / f"{name}.csv") and entry["events_file"] == str(tmp_path / f"{name}.npz")
        assert entry["events_in_file"] == len(stream[0]) and entry["sensor_hw"] == [480, 640]  # npz states none: EE3D's
        assert entry["first_window_start_us"] == int(starts[0])


SEVERAL_FILES_ERRORS = {  # case: words the error line must contain
    "same_file": "same file", "same_file_other_spelling": "same file", "extension_only": "only in their extension",
    "one_too_short": "no complete", "out_exists": "--force", "chunk_events": "--chunk-events must be positive",
    "threads": "--threads: expected a positive whole number", "render": "single --events file",
    "render_max_frames": "single --events file",
}


@pytest.mark.parametrize("case", sorted(SEVERAL_FILES_ERRORS))
def test_cli_several_files_fail_cleanly(case, tiny_graph, tmp_path, capsys):
    stream = synthetic_stream(seed=41, windows=7)
    (tmp_path / "other").mkdir()
    files = [write_npz(tmp_path / "one.npz", *stream), write_npz(tmp_path / "two.npz", *stream)]
    out, options = tmp_path / "poses", []
    if case == "same_file":
        files[1] = files[0]
    elif case == "same_file_other_spelling":
        files[1] = tmp_path / "other" / ".." / "one.npz"
    elif case == "extension_only":
        files[1] = tmp_path / "one.h5"
        write_events_h5(files[1], EventStream(*stream))
    elif case in ("chunk_events", "threads"):
        options = [f"--{case.replace('_', '-')}", "0"]
    elif case == "render":
        options = ["--render", str(tmp_path / "poses.gif")]
    elif case == "render_max_frames":
        options = ["--render-max-frames", "3"]
    elif case == "one_too_short":
        files[1] = write_npz(tmp_path / "two.npz", *(a[:5] for a in stream))
    else:
        out.mkdir()
        (out / "two.csv").write_text("keep me")
    inputs = sorted(p.name for p in tmp_path.rglob("*"))
    code = _exit_code(["run", "--model", str(tiny_graph[1]), "--events", *map(str, files), "--out", str(out),
                       *options])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("e3dpsm run: error:"), err
    assert SEVERAL_FILES_ERRORS[case] in err[0], err
    assert sorted(p.name for p in tmp_path.rglob("*")) == inputs  # nothing written, no temporary left
    if case == "out_exists":
        assert (out / "two.csv").read_text() == "keep me"


def test_cli_names_csvs_by_sequence_folder(tiny_graph, tmp_path, capsys):
    """Every sequence is <sequence>/events.h5: the CSVs are named by the sequence folders and
    hold the same poses as running each file alone."""
    files = []
    for name, seed in (("seq_0000", 51), ("seq_0001", 52)):
        (tmp_path / "data" / name).mkdir(parents=True)
        files.append(write_events_h5(tmp_path / "data" / name / "events.h5",
                                     EventStream(*synthetic_stream(seed=seed, windows=8))))
    model, out = str(tiny_graph[1]), tmp_path / "poses"
    code = main(["run", "--model", model, "--events", *map(str, files), "--out", str(out), "--threads", "1"])
    assert code == 0, capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["run.report.json", "seq_0000.csv", "seq_0001.csv"]
    report = json.loads((out / "run.report.json").read_text())
    assert {entry["events_file"]: entry["csv"] for entry in report["streams"].values()} == {
        str(files[0]): str(out / "seq_0000.csv"), str(files[1]): str(out / "seq_0001.csv")}
    for name, events in zip(("seq_0000", "seq_0001"), files):
        alone = tmp_path / f"{name}_alone.csv"
        code = main(["run", "--model", model, "--events", str(events), "--out", str(alone), "--threads", "1"])
        assert code == 0, capsys.readouterr().err
        header, table = read_csv(out / f"{name}.csv")
        alone_header, alone_table = read_csv(alone)
        assert header == alone_header and table.shape == alone_table.shape and len(table) >= 4
        assert table[:, 0].tolist() == alone_table[:, 0].tolist()
        np.testing.assert_allclose(table[:, 1:], alone_table[:, 1:], rtol=0, atol=CSV_TOL_MM)


@pytest.mark.parametrize("events, names", [
    (["data/seq_0000/events.h5", "data/seq_0001/events.h5"], ["seq_0000", "seq_0001"]),  # one stem: folders
    (["walk.npz", "data/sit.h5", "a/b/jump.hdf5"], ["walk", "sit", "jump"]),  # stems differ: plain stems
    (["a/seq_0000/events.h5", "b/seq_0000/events.h5", "a/seq_0001/events.h5"],  # deeper clash: joined
     ["a__seq_0000", "b__seq_0000", "seq_0001"]),
    (["x/walk.npz", "y/walk.npz", "x/sit.npz"], ["x__walk", "y__walk", "sit"]),  # clash only among some
    (["/data/events.h5", "/x/data/events.h5"], ["data", "x__data"]),  # one path ends the other
    (["/r/a/seq/events.h5", "/r/b/seq/events.h5"], ["a", "b"]),  # every shared trailing part dropped
])
def test_stream_names_rule(events, names):
    assert stream_names(events) == names


@pytest.mark.parametrize("events, words", [
    (["a/events.h5", "a/events.h5"], "same file"),
    (["a/events.h5", "a/x/../events.h5"], "same file"),
    (["a/events.h5", "a/events.npz"], "only in their extension"),
    (["a/seq/events.h5", "a/Seq/events.h5"], "letter case"),
    (["a__b.h5", "a/b.h5", "c/b.h5"], "both write a__b.csv"),  # a/b is named a__b after the clash with c/b
])
def test_stream_names_refuses_paths_it_cannot_tell_apart(events, words):
    with pytest.raises(ConfigError, match=re.escape(words)):
        stream_names(events)


@pytest.mark.parametrize("events, message", [
    (["a/events.h5", "b.h5", "a/x/../events.h5"], "--events a/x/../events.h5 is the same file as a/events.h5; give each "
                                                 "event file once"),
    (["x/events.h5", "b.h5", "x/events.npz"], "--events x/events.h5 and x/events.npz differ only in their extension; "
                                              "each CSV is named by folder and file names, so rename or link one of them"),
    (["a/seq/events.h5", "b.h5", "a/Seq/events.h5"], "--events a/seq/events.h5 and a/Seq/events.h5 would both write "
                                                     "Seq__events.csv (CSV names are compared ignoring letter case, for "
                                                     "case-insensitive file systems); rename or link one of them"),
])
def test_stream_names_refusals_name_both_files_whole(tmp_path, monkeypatch, events, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a" / "x").mkdir(parents=True)
    assert stream_names(["/d/x/y/z/events.h5", "/d/w/y/z/events.h5"]) == ["x", "w"]  # three trailing parts shared
    with pytest.raises(ConfigError) as error:
        stream_names(events)
    assert str(error.value) == message


def test_the_output_folder_refusals_whole(tmp_path):
    from e3dpsm.errors import DataError, OutputExistsError
    from e3dpsm.runtime.run_many import _outputs

    events = (str(tmp_path / "walk.npz"), str(tmp_path / "sit.npz"))
    request = type("Request", (), {"events": events, "force": False, "out": tmp_path / "poses.csv"})()
    request.out.write_text("a file")
    with pytest.raises(DataError) as error:
        _outputs(request)
    assert str(error.value) == (f"--out {request.out} is a file; with several --events files it names a folder of "
                                "CSVs")
    request.out = tmp_path / "poses"
    request.out.mkdir()
    (request.out / "run.report.json").write_text("{}")
    with pytest.raises(OutputExistsError) as error:
        _outputs(request)
    assert str(error.value) == f"{request.out / 'run.report.json'} exists; pass --force to replace it"
    request.force = True
    assert _outputs(request) == ({"walk": events[0], "sit": events[1]},
                                 {"walk": request.out / "walk.csv", "sit": request.out / "sit.csv"})


def _exit_code(argv: list[str]) -> int:
    """main's return code, or argparse's exit code for an argument it refused (one line too)."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)
