"""What the forms of `e3dpsm run` (run_file.py, run_many.py, run_live.py) share: the gap check,
event chunking, the CSV's columns and rows, the report's common parts and the no-window error.
Torch-free: the standard library and numpy (imported where it is used); onnxruntime comes in
through the objects passed in.
"""
from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator

from e3dpsm.errors import DataError

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.data.sequence import EventStream
    from e3dpsm.runtime.run_command import RunRequest
    from e3dpsm.runtime.stream import EventChunk, PoseEstimate, StreamingPoseEstimator, StreamStats

PRECISION = 4  # decimals of a joint coordinate (mm) in the CSV


def check_gaps(t_us: Any, max_gap_s: float, window_ms: float, source: str, previous_us: int | None = None) -> None:
    """Refuse a silence longer than `max_gap_s` between two events (`previous_us`: the last one
    before `t_us`). `run` steps every empty window of a silence (runtime/stream.py), so one
    corrupted timestamp (a flipped high bit: hours, or centuries) would keep it stepping for
    as long; an event camera's background activity never leaves it silent for a minute."""
    import numpy as np

    times = np.asarray(t_us, dtype=np.int64)
    if previous_us is not None and times.size:
        times = np.concatenate([[previous_us], times])
    if times.size < 2:
        return
    gaps = np.diff(times)
    widest = int(np.argmax(gaps))
    if gaps[widest] > max_gap_s * 1e6:
        gap_s, first = gaps[widest] / 1e6, widest - (previous_us is not None)
        where = f"events {first} and {first + 1}" if first >= 0 else "event 0 and the event before it"
        raise DataError(
            f"{source}: {where} are {gap_s:.6g} s apart: {gap_s * 1e3 / window_ms:,.0f} empty {window_ms:g} ms windows "
            f"to step. No event camera is silent that long: a timestamp is corrupted, or pass --max-gap-s "
            f"{math.ceil(gap_s)} to run it as it is")


def event_chunks(stream: EventStream, size: int) -> Iterator[EventChunk]:
    """The stream as (x, y, t_us, p) slices of at most `size` events."""
    for lo in range(0, len(stream), size):
        hi = lo + size
        yield stream.x[lo:hi], stream.y[lo:hi], stream.t_us[lo:hi], stream.p[lo:hi]


def pose_columns(joints: list[str]) -> list[str]:
    return ["t_us", *(f"{joint}_{axis}" for joint in joints for axis in "xyz")]


def pose_row(pose: PoseEstimate) -> list[Any]:
    return [pose.t_us, *(f"{v:.{PRECISION}f}" for v in pose.pose.reshape(-1).tolist())]


def write_pose_csv(path: str | os.PathLike, joints: list[str], poses: Iterable[PoseEstimate]) -> None:
    """Rows go to the file as they come, so memory stays flat on long recordings."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(pose_columns(joints))
        for pose in poses:
            writer.writerow(pose_row(pose))


def report_path(out: Path) -> Path:
    """The one-stream forms' report, beside the CSV: poses.csv -> poses.report.json."""
    return out.with_name(out.stem + ".report.json")


def report_head(request: RunRequest, out: Path, estimator: Any, events: str | list[str]) -> dict[str, Any]:
    """The part of run's JSON report every form writes: header with the config, graph, policies.

    `estimator` is a StreamingPoseEstimator or a MultiStreamEstimator (same session, window_ms,
    frame_hw attributes)."""
    from e3dpsm.utils.env import report_header

    meta = estimator.session.meta
    config = {
        "model": str(request.model), "events": events, "out": str(out), "window_ms": estimator.window_ms,
        "threads": request.threads, "start_us": request.start_us, "chunk_events": request.chunk_events,
    }
    return {
        **report_header("run", config),
        "graph": {"variant": meta.config.get("variant"), "quantization": meta.quantization,
                  "frame_hw": list(estimator.frame_hw)},
        "pose_timestamp": "window end",
        "empty_window_policy": "stepped with an all-zero LNES frame (states decay, fusion runs)",
    }


def stream_report(request: RunRequest, estimator: StreamingPoseEstimator, source: str,
                  **middle: Any) -> dict[str, Any]:
    """The one-stream forms' report: the head, the stream's grid, `middle` (what the form adds),
    then the estimator's statistics."""
    summary = estimator.stats.to_dict()
    return {
        **report_head(request, request.out, estimator, source),
        "sensor_hw": list(estimator.sensor_hw),
        "first_window_start_us": estimator.first_window_start_us,
        **middle,
        **summary,
        "overhead_ms": summary["mean_overhead_ms"],  # per window: validation, windowing, LNES, feeds
    }


def no_window_error(events: str, stream: EventStream, window_ms: float, stats: StreamStats) -> DataError:
    """Why a stream gave no pose, for the documented error (not an empty CSV)."""
    if not len(stream):
        return DataError(f"{events}: the event stream is empty; nothing to estimate")
    span = int(stream.t_us[-1] - stream.t_us[0])
    skipped = stats.events_before_start
    before = f", {skipped} of them before --start-us" if skipped else ""
    return DataError(
        f"{events}: no complete {window_ms:g} ms window in {len(stream)} events spanning "
        f"{span} us{before}; nothing to estimate"
    )
