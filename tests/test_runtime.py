"""Streaming runtime (e3dpsm.runtime.stream) and `e3dpsm run`: same poses as stepping the
graph directly and as the PyTorch step, torch-free, and clean failures on bad input."""
from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import onnx
import pytest

from e3dpsm.cli import main
from e3dpsm.errors import InputError
from e3dpsm.runtime import StreamingPoseEstimator
from _runtime_helpers import (
    WINDOW_US, chunked, exported_tiny, reference_frames, shared_session, step_frames, synthetic_stream,
)

SAME_GRAPH_TOL_MM = 1e-5  # the same graph on the same frames: only run-to-run round-off
PYTORCH_PARITY_TOL_MM = 0.01  # ORT vs PyTorch kernels, float32 (project parity tolerance)


@pytest.fixture(scope="session")
def tiny_graph(tmp_path_factory) -> tuple[object, Path]:
    return exported_tiny(str(tmp_path_factory.getbasetemp()))


@pytest.fixture(scope="session")
def session(tiny_graph):
    return shared_session(str(tiny_graph[1]))


@pytest.fixture(scope="module")
def stream():
    return synthetic_stream(seed=3, windows=12)


def run_chunks(session, chunks, **kwargs):
    estimator = StreamingPoseEstimator(session, **kwargs)
    poses = list(estimator.run(chunks))
    return estimator, poses


def test_random_chunks_match_direct_stepping(session, stream):
    starts, counts, frames = reference_frames(*stream)
    expected, _ = step_frames(session, frames)
    rng = np.random.default_rng(0)
    cuts = rng.integers(0, stream[2].size, 7)
    estimator, poses = run_chunks(session, chunked(stream, cuts), window_ms=20.0)

    assert [p.t_us for p in poses] == (starts + WINDOW_US).tolist()  # timestamped at window END
    assert [p.events for p in poses] == counts.tolist()
    np.testing.assert_allclose(np.stack([p.pose for p in poses]), expected, rtol=0, atol=SAME_GRAPH_TOL_MM)
    assert estimator.stats.windows == len(starts)
    assert estimator.stats.empty_windows == int((counts == 0).sum()) >= 1  # the gap was stepped, not skipped
    assert estimator.stats.events == int(counts.sum())


def test_matches_pytorch_step(tiny_graph, session, stream):
    import torch

    model = tiny_graph[0]
    head = stream[2] < stream[2][0] + 4 * WINDOW_US + 1  # four windows: the PyTorch step is slow on CPU
    _, _, frames = reference_frames(*(a[head] for a in stream))
    state = model.init_state(1)
    expected = []
    with torch.no_grad():
        for frame in frames:
            outputs, state = model.step(torch.from_numpy(frame[None]), state, WINDOW_US / 1000)
            expected.append(outputs["pose"][0].numpy())
    _, poses = run_chunks(session, [tuple(a[head] for a in stream)])
    got = np.stack([p.pose for p in poses])
    assert got.shape == (len(frames), 16, 3)
    np.testing.assert_allclose(got, np.stack(expected), rtol=0, atol=PYTORCH_PARITY_TOL_MM)


def test_empty_window_steps_with_a_zero_frame(session, stream):
    """A silent window is one model step on an all-zero LNES frame: the estimate moves."""
    x, y, t, p = stream
    first = t[0]
    head = t < first + 2 * WINDOW_US  # two windows of events, then nothing for two windows
    estimator = StreamingPoseEstimator(session)
    poses = estimator.push(x[head], y[head], t[head], p[head]) + estimator.flush(int(first) + 4 * WINDOW_US)
    assert [q.events for q in poses][2:] == [0, 0]

    _, _, frames = reference_frames(x[head], y[head], t[head], p[head], end_us=int(first) + 4 * WINDOW_US)
    assert not frames[2:].any()
    expected, _ = step_frames(session, frames)
    np.testing.assert_allclose(np.stack([q.pose for q in poses]), expected, rtol=0, atol=SAME_GRAPH_TOL_MM)
    assert np.abs(poses[3].pose - poses[1].pose).max() > 1e-3  # not frozen at the last estimate


def test_flush_closes_windows_and_later_events_must_follow(session, stream):
    x, y, t, p = stream
    estimator = StreamingPoseEstimator(session)
    estimator.push(x[:50], y[:50], t[:50], p[:50])
    poses = estimator.flush(int(t[0]) + 3 * WINDOW_US)
    assert [q.t_us for q in poses] == [int(t[0]) + k * WINDOW_US for k in (1, 2, 3)]
    late = int(np.searchsorted(t, t[0] + 2 * WINDOW_US))  # an event inside a window already emitted
    with pytest.raises(InputError, match="out of order"):
        estimator.push(x[late:], y[late:], t[late:], p[late:])


def test_start_us_skips_earlier_events_and_sets_the_grid(session, stream):
    x, y, t, p = stream
    start = int(t[0]) + 30_000
    starts, counts, frames = reference_frames(x, y, t, p, start_us=start)
    estimator, poses = run_chunks(session, chunked(stream, [100, 900]), start_us=start)
    assert poses[0].t_start_us == start
    assert [q.events for q in poses] == counts.tolist()
    assert estimator.stats.events_before_start == int((t < start).sum()) > 0
    np.testing.assert_allclose(
        np.stack([q.pose for q in poses]), step_frames(session, frames)[0], rtol=0, atol=SAME_GRAPH_TOL_MM
    )


def test_signed_polarity_equals_channel_polarity(session, stream):
    x, y, t, p = stream
    _, reference = run_chunks(session, [stream])
    _, signed = run_chunks(session, [(x, y, t, np.where(p > 0, 1, -1))])
    np.testing.assert_array_equal(np.stack([q.pose for q in signed]), np.stack([q.pose for q in reference]))


def test_reset_starts_a_fresh_stream(session, stream):
    estimator = StreamingPoseEstimator(session)
    first = [q.pose for q in estimator.run([stream])]
    estimator.reset()
    assert estimator.stats.windows == 0
    again = [q.pose for q in estimator.run([stream])]
    np.testing.assert_array_equal(np.stack(again), np.stack(first))


@pytest.mark.parametrize("bad", ["unsorted", "nan", "out_of_range", "polarity"])
def test_bad_chunks_raise_input_error(session, stream, bad):
    x, y, t, p = (np.array(a[:100], dtype=np.float64) for a in stream)
    if bad == "unsorted":
        t[[10, 20]] = t[[20, 10]] + [0, 1]
    elif bad == "nan":
        y[5] = np.nan
    elif bad == "out_of_range":
        x[7] = 640
    else:
        p[3] = 2
    estimator = StreamingPoseEstimator(session)
    with pytest.raises(InputError):
        estimator.push(x, y, t, p)
    assert estimator.windower.last_t_us is None and estimator.stats.events_received == 0  # nothing consumed


# -- torch-free and metadata-only operation ---------------------------------------------------

def test_runtime_imports_no_torch():
    # `run`'s body is library code: its forms load without the CLI, and neither pulls in torch.
    code = ("import sys, e3dpsm.runtime, e3dpsm.runtime.stream, e3dpsm.runtime.run_command, e3dpsm.runtime.run_file, "
            "e3dpsm.runtime.run_many, e3dpsm.runtime.run_live; "
            "cli = [m for m in sys.modules if m.startswith('e3dpsm.cli')]; assert not cli, cli; "
            "import e3dpsm.cli.run; assert 'torch' not in sys.modules, 'torch imported'")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


PURE_ORT_DRIVER = textwrap.dedent('''
    # Drives the step graph knowing only onnxruntime, numpy and the graph's metadata.
    import json, sys
    import numpy as np
    import onnxruntime as ort

    graph, frames_path, steps, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
    sess = ort.InferenceSession(graph, providers=["CPUExecutionProvider"])
    meta = sess.get_modelmeta().custom_metadata_map
    states = json.loads(meta["e3dpsm.states"])
    inputs = json.loads(meta["e3dpsm.inputs"])
    pose_name = json.loads(meta["e3dpsm.outputs"])[0]["name"]

    def initial(entry):
        shape = [1 if d == "batch" else d for d in entry["shape"]]
        if entry["init"] == "zeros":
            return np.zeros(shape, entry["dtype"])
        return np.broadcast_to(np.asarray(entry["init"], entry["dtype"]).reshape(shape[1:]), shape).copy()

    state = {e["input"]: initial(e) for e in states}
    frames = np.load(frames_path)["frames"]
    names = [o.name for o in sess.get_outputs()]
    window = np.array([inputs["window"]["train_window_ms"]], np.float32)
    poses = []
    for i in range(steps):
        feeds = {inputs["frame"]["name"]: frames[i % len(frames)][None], inputs["window"]["name"]: window, **state}
        result = dict(zip(names, sess.run(names, feeds)))
        state = {e["input"]: result[e["output"]] for e in states}
        poses.append(result[pose_name][0])
    assert not [m for m in sys.modules if m.split(".")[0] in ("e3dpsm", "torch")], "must run without e3dpsm"
    np.savez(out, poses=np.stack(poses), **{e["name"]: state[e["input"]] for e in states})
''')


def test_graph_runs_with_onnxruntime_and_metadata_alone(tiny_graph, session, stream, tmp_path):
    steps = 200
    _, _, frames = reference_frames(*stream)
    frames = np.concatenate([frames, np.zeros((1, *frames.shape[1:]), np.float32)])
    np.savez_compressed(tmp_path / "frames.npz", frames=frames)
    (tmp_path / "driver.py").write_text(PURE_ORT_DRIVER)
    done = subprocess.run(
        [sys.executable, "-I", "driver.py", str(tiny_graph[1]), "frames.npz", str(steps), "out.npz"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 0, done.stderr
    result = np.load(tmp_path / "out.npz")
    expected, state = step_frames(session, frames[np.arange(steps) % len(frames)])
    np.testing.assert_allclose(result["poses"], expected, rtol=0, atol=SAME_GRAPH_TOL_MM)
    for name, value in state.items():  # the whole recurrent state, not only the outputs
        np.testing.assert_allclose(result[name], value, rtol=0, atol=1e-6)


# -- e3dpsm run ---------------------------------------------------------------------------------

def write_npz(path: Path, x, y, t, p) -> Path:
    np.savez(path, x=x, y=y, t=t, p=p)
    return path


def test_cli_writes_poses_and_report(tiny_graph, session, stream, tmp_path, capsys):
    events = write_npz(tmp_path / "events.npz", *stream)
    out = tmp_path / "out" / "poses.csv"
    code = main(["run", "--model", str(tiny_graph[1]), "--events", str(events), "--out", str(out),
                 "--chunk-events", "700", "--threads", "1"])
    assert code == 0, capsys.readouterr().err
    starts, counts, frames = reference_frames(*stream)
    expected, _ = step_frames(session, frames)
    with open(out, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0][:4] == ["t_us", "Head_x", "Head_y", "Head_z"] and rows[0][-1] == "L_foot_z"
    assert len(rows[0]) == 1 + 16 * 3
    table = np.array(rows[1:], dtype=np.float64)
    assert table[:, 0].astype(np.int64).tolist() == (starts + WINDOW_US).tolist()
    np.testing.assert_allclose(table[:, 1:].reshape(-1, 16, 3), expected, rtol=0, atol=1e-4)  # 4 decimals in CSV

    report = json.loads((tmp_path / "out" / "poses.report.json").read_text())
    assert report["command"] == "run" and "versions" in report
    assert report["config"] == {"model": str(tiny_graph[1]), "events": str(events), "out": str(out), "window_ms": 20.0,
                                "threads": 1, "start_us": None, "chunk_events": 700}
    assert report["windows"] == len(starts) and report["empty_windows"] == int((counts == 0).sum())
    assert report["events"] == int(counts.sum()) and report["events_in_file"] == stream[2].size
    assert report["mean_step_ms"] > 0 and report["overhead_ms"] >= 0
    step, window = report["step_ms"], report["window_ms"]  # per window: the step, and LNES + feeds + step
    assert step["count"] == window["count"] == len(starts)
    assert 0 < step["p50"] <= window["p50"] and step["max"] <= window["max"]
    assert step["max"] + 1e-3 >= report["mean_step_ms"]  # the largest (exact, 3 decimals) of the steps averaged
    assert sorted(p.name for p in out.parent.iterdir()) == ["poses.csv", "poses.report.json"]


def test_run_is_one_library_call_that_writes_what_the_command_writes(tiny_graph, stream, tmp_path, capsys):
    from e3dpsm.runtime.run_command import RunRequest, run_poses

    events = write_npz(tmp_path / "events.npz", *stream)
    assert main(["run", "--model", str(tiny_graph[1]), "--events", str(events), "--out", str(tmp_path / "cli.csv"),
                 "--threads", "1", "--no-progress"]) == 0
    printed = capsys.readouterr().out.splitlines()
    result = run_poses(RunRequest(model=str(tiny_graph[1]), events=(str(events),), out=str(tmp_path / "lib.csv"),
                                  threads=1))
    assert (tmp_path / "lib.csv").read_text() == (tmp_path / "cli.csv").read_text()
    assert result.report == json.loads((tmp_path / "lib.report.json").read_text())  # the report as written
    cli_report = json.loads((tmp_path / "cli.report.json").read_text())
    assert result.report.keys() == cli_report.keys() and result.report["config"].keys() == cli_report["config"].keys()
    assert len(printed) == len(result.summary) == 1
    assert result.summary[0].split(" at ")[0] == printed[0].split(" at ")[0]  # counts agree; timings differ
    assert result.summary[0].endswith(f"-> {tmp_path / 'lib.csv'}")


def test_the_summary_line_and_the_progress_bar(tiny_graph, stream, tmp_path, capsys):
    from e3dpsm.runtime.run_command import RunRequest, run_poses

    events = write_npz(tmp_path / "events.npz", *stream)
    request = dict(model=str(tiny_graph[1]), events=(str(events),), threads=1, chunk_events=500)
    plain = run_poses(RunRequest(**request, out=tmp_path / "plain.csv"))
    r = plain.report
    assert plain.summary == (f"{r['windows']} poses ({r['empty_windows']} empty windows, {r['events']} events) at "
                             f"{r['mean_step_ms']:.2f} ms/step + {r['overhead_ms']:.2f} ms runtime overhead "
                             f"-> {tmp_path / 'plain.csv'}",)
    assert "run:" not in capsys.readouterr().err  # a library call draws no bar unless asked
    shown = run_poses(RunRequest(**request, out=tmp_path / "bar.csv", progress=True))
    bar = capsys.readouterr().err
    assert (tmp_path / "bar.csv").read_text() == (tmp_path / "plain.csv").read_text()
    assert shown.report["windows"] == r["windows"]
    # The bar counts every event of the file, in the chunks the stream was read in.
    total = stream[2].size
    assert total > 500 and re.search(rf"(^|\r)run: 100%\|[^|]*\| {total / 1000:.2f}k/{total / 1000:.2f}k \[[^\]]*ev/s\]",
                                     bar), bar


def test_the_documented_defaults_of_run_are_the_requests(tiny_graph, stream, tmp_path):
    """docs/bad-input.md: silences over 60 s are refused by default; docs/cameras.md: a live
    source waits 5 s."""
    from e3dpsm.errors import DataError
    from e3dpsm.runtime.run_command import LIVE_TIMEOUT_S, RunRequest, run_poses

    x, y, t, p = stream
    late = t.copy()
    late[len(t) // 2:] += 60_500_000  # a silence of 60.5 s (and a bit) in the middle
    events = write_npz(tmp_path / "events.npz", x, y, late, p)
    with pytest.raises(DataError, match=r"are 60\.5\d* s apart: .* pass --max-gap-s 61 "):
        run_poses(RunRequest(model=str(tiny_graph[1]), events=(str(events),), out=tmp_path / "p.csv", threads=1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["events.npz"]
    cameras = (Path(__file__).parents[1] / "docs" / "cameras.md").read_text(encoding="utf-8")
    assert f"no events from dv://... for {LIVE_TIMEOUT_S:g} s" in cameras
    assert f"no stream header came within {LIVE_TIMEOUT_S:g} s" in cameras


def stripped_graph(path: Path, folder: Path) -> Path:
    model = onnx.load(str(path))
    del model.metadata_props[:]
    onnx.save(model, str(folder / "no_meta.onnx"))
    return folder / "no_meta.onnx"


BAD_INPUTS = {
    # case: (how to break the inputs, words the error line must contain)
    "nan": ("x", "non-finite"),
    "inf": ("t", "non-finite"),
    "out_of_range": ("x", "outside the sensor"),
    "unsorted": ("t", "non-decreasing"),
    "polarity": ("p", "polarity"),
    "empty": (None, "empty"),
    "too_short": (None, "no complete"),
    "no_metadata": (None, "metadata"),
    "missing_events": (None, "does not exist"),
    "missing_model": (None, "does not exist"),
    "out_under_file": (None, "is a file"),
    "out_exists": (None, "--force"),
    "chunk_events": (None, "--chunk-events must be positive"),
    "threads": (None, "--threads: expected a positive whole number"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_cli_bad_input_fails_cleanly(case, tiny_graph, stream, tmp_path, capsys):
    x, y, t, p = (np.asarray(a[:2000], dtype=np.float64) for a in stream)
    model, out_dir = tiny_graph[1], tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / "poses.csv"
    if case == "nan":
        x[11] = np.nan
    elif case == "inf":
        t[-1] = np.inf
    elif case == "out_of_range":
        x[5] = 700
    elif case == "unsorted":
        t[[100, 900]] = t[[900, 100]]
    elif case == "polarity":
        p[3] = 2
    elif case == "empty":
        x, y, t, p = (a[:0] for a in (x, y, t, p))
    elif case == "too_short":
        x, y, t, p = (a[:5] for a in (x, y, t, p))
    elif case == "no_metadata":
        model = stripped_graph(model, tmp_path)
    elif case == "missing_model":
        model = tmp_path / "nope.onnx"
    elif case == "out_under_file":
        (out_dir / "plain_file").write_text("x")
        out = out_dir / "plain_file" / "poses.csv"
    elif case == "out_exists":
        out.write_text("keep me")
    events = write_npz(tmp_path / "events.npz", x, y, t, p)
    if case == "missing_events":
        events = tmp_path / "missing.npz"

    options = [f"--{case.replace('_', '-')}", "0"] if case in ("chunk_events", "threads") else []
    code = _exit_code(["run", "--model", str(model), "--events", str(events), "--out", str(out), *options])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("e3dpsm run: error:"), err
    assert BAD_INPUTS[case][1] in err[0]
    leftovers = sorted(q.name for q in out_dir.iterdir())
    assert leftovers == {"out_under_file": ["plain_file"], "out_exists": ["poses.csv"]}.get(case, [])
    if case == "out_exists":
        assert out.read_text() == "keep me"


def _exit_code(argv: list[str]) -> int:
    """main's return code, or argparse's exit code for an argument it refused (one line too)."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)
