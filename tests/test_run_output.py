"""What the forms of `e3dpsm run` share (runtime/run_output.py), on hand-made inputs: the gap
check at its bound, chunking, the CSV's columns and rows, the report's common parts and the
no-window errors, each message compared whole."""
from __future__ import annotations

import csv
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from e3dpsm.errors import DataError
from e3dpsm.runtime.run_output import (PRECISION, check_gaps, event_chunks, no_window_error, pose_columns, pose_row,
                                       report_head, report_path, stream_report, write_pose_csv)


class Stream(SimpleNamespace):
    """What the helpers read of an EventStream: its arrays and its length."""

    def __len__(self) -> int:
        return len(self.t_us)


def _gap_message(source: str, where: str, gap_s: float, window_ms: float, flag: int) -> str:
    windows = f"{gap_s * 1e3 / window_ms:,.0f}"
    return (f"{source}: {where} are {gap_s:.6g} s apart: {windows} empty {window_ms:g} ms windows to step. No event "
            f"camera is silent that long: a timestamp is corrupted, or pass --max-gap-s {flag} to run it as it is")


def test_a_silence_up_to_the_bound_passes_and_one_microsecond_more_is_refused() -> None:
    check_gaps([0, 10, 60_000_010], 60.0, 20.0, "rec.h5")  # exactly 60 s
    with pytest.raises(DataError) as refused:
        check_gaps([0, 10, 60_000_011, 60_000_020], 60.0, 20.0, "rec.h5")
    assert str(refused.value) == _gap_message("rec.h5", "events 1 and 2", 60.000001, 20.0, 61)


def test_the_widest_gap_is_named_and_the_previous_chunks_last_event_counts() -> None:
    with pytest.raises(DataError) as refused:  # two gaps over the bound: the wider one
        check_gaps([0, 3_000_000, 3_000_001, 10_500_001], 2.0, 50.0, "a.raw")
    assert str(refused.value) == _gap_message("a.raw", "events 2 and 3", 7.5, 50.0, 8)
    with pytest.raises(DataError) as refused:  # the chunk's first two events
        check_gaps([0, 4_000_000, 4_000_001], 2.0, 20.0, "a.raw")
    assert str(refused.value) == _gap_message("a.raw", "events 0 and 1", 4.0, 20.0, 4)
    with pytest.raises(DataError) as refused:  # the silence lies between two chunks
        check_gaps([5_000_000, 5_000_010], 1.0, 25.0, "b.dat", previous_us=1_000_000)
    assert str(refused.value) == _gap_message("b.dat", "event 0 and the event before it", 4.0, 25.0, 4)
    with pytest.raises(DataError) as refused:  # within the chunk, after a previous event
        check_gaps([10, 20, 9_000_020], 1.0, 25.0, "c.dat", previous_us=0)
    assert str(refused.value) == _gap_message("c.dat", "events 1 and 2", 9.0, 25.0, 9)
    check_gaps([], 1.0, 20.0, "d", previous_us=0)  # nothing new
    check_gaps([5], 1.0, 20.0, "d")  # one event: no gap
    with pytest.raises(DataError):
        check_gaps([5_000_000], 1.0, 20.0, "d", previous_us=0)  # one event after the previous one


def test_chunks_cover_the_stream_in_order() -> None:
    n = 7
    stream = Stream(x=np.arange(n), y=np.arange(n) + 10, t_us=np.arange(n) * 100, p=np.arange(n) % 2)
    chunks = list(event_chunks(stream, 3))
    assert [len(c[0]) for c in chunks] == [3, 3, 1]
    for part, field in enumerate(("x", "y", "t_us", "p")):
        np.testing.assert_array_equal(np.concatenate([c[part] for c in chunks]), getattr(stream, field))
    assert [c[2][0] for c in chunks] == [0, 300, 600]


def test_the_csv_has_a_column_per_joint_axis_and_rows_as_they_come(tmp_path) -> None:
    assert pose_columns(["Head", "Neck"]) == ["t_us", "Head_x", "Head_y", "Head_z", "Neck_x", "Neck_y", "Neck_z"]
    pose = SimpleNamespace(t_us=20_000, pose=np.array([[1.0, -2.5, 3.123456], [0.0, 10.0, -0.00004]]))
    assert PRECISION == 4
    assert pose_row(pose) == [20_000, "1.0000", "-2.5000", "3.1235", "0.0000", "10.0000", "-0.0000"]
    later = SimpleNamespace(t_us=40_000, pose=np.zeros((2, 3)))
    write_pose_csv(tmp_path / "poses.csv", ["Head", "Neck"], iter([pose, later]))
    with open(tmp_path / "poses.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    assert rows == [pose_columns(["Head", "Neck"]), [str(v) for v in pose_row(pose)], [str(v) for v in pose_row(later)]]
    assert (tmp_path / "poses.csv").read_bytes().count(b"\r\n") == 3  # csv's own line ends, no blank lines


def test_the_report_sits_beside_the_csv() -> None:
    assert report_path(Path("out/poses.csv")) == Path("out/poses.report.json")
    assert report_path(Path("a.b.csv")) == Path("a.b.report.json")


class _Stats:
    def to_dict(self) -> dict:
        return {"windows": 12, "mean_overhead_ms": 0.75, "mean_step_ms": 4.0}


def _estimator() -> SimpleNamespace:
    meta = SimpleNamespace(config={"variant": "tiny", "other": 1}, quantization={"mode": "int8"})
    return SimpleNamespace(session=SimpleNamespace(meta=meta), window_ms=25.0, frame_hw=(192, 256),
                           sensor_hw=(480, 640), first_window_start_us=1_000, stats=_Stats())


REQUEST = SimpleNamespace(model=Path("m.onnx"), threads=2, start_us=500, chunk_events=4096, out=Path("o/poses.csv"))


def test_the_report_head_names_the_run_its_graph_and_policies() -> None:
    head = report_head(REQUEST, Path("o/poses.csv"), _estimator(), ["a.h5", "b.h5"])
    assert head["command"] == "run" and {"created", "versions", "machine"} <= set(head)
    assert head["config"] == {"model": "m.onnx", "events": ["a.h5", "b.h5"], "out": "o/poses.csv", "window_ms": 25.0,
                              "threads": 2, "start_us": 500, "chunk_events": 4096}
    assert head["graph"] == {"variant": "tiny", "quantization": {"mode": "int8"}, "frame_hw": [192, 256]}
    assert head["pose_timestamp"] == "window end"
    assert head["empty_window_policy"] == "stepped with an all-zero LNES frame (states decay, fusion runs)"


def test_the_one_stream_report_orders_head_grid_middle_and_statistics() -> None:
    report = stream_report(REQUEST, _estimator(), "rec.h5", source_format="hdf5", windows=99)
    head = report_head(REQUEST, REQUEST.out, _estimator(), "rec.h5")
    assert {k: v for k, v in report.items() if k not in ("created", "machine")} == {
        **{k: v for k, v in head.items() if k not in ("created", "machine")},
        "sensor_hw": [480, 640], "first_window_start_us": 1_000, "source_format": "hdf5",
        "windows": 12,  # the estimator's own count wins over a form's
        "mean_overhead_ms": 0.75, "mean_step_ms": 4.0, "overhead_ms": 0.75}
    assert list(report)[-1] == "overhead_ms" and report["config"]["events"] == "rec.h5"


def test_why_a_stream_gave_no_pose() -> None:
    empty = Stream(t_us=np.array([], np.int64))
    assert str(no_window_error("e.h5", empty, 20.0, SimpleNamespace(events_before_start=0))) == (
        "e.h5: the event stream is empty; nothing to estimate")
    short = Stream(t_us=np.array([100, 400, 15_100], np.int64))
    assert str(no_window_error("s.h5", short, 20.0, SimpleNamespace(events_before_start=0))) == (
        "s.h5: no complete 20 ms window in 3 events spanning 15000 us; nothing to estimate")
    assert str(no_window_error("s.h5", short, 12.5, SimpleNamespace(events_before_start=2))) == (
        "s.h5: no complete 12.5 ms window in 3 events spanning 15000 us, 2 of them before --start-us; "
        "nothing to estimate")
