"""What `e3dpsm run` shares between its one-file form (run.py) and its many-file form
(_run_many.py): option checks, event chunking, CSV rows, the report's common part and the
no-window error, the gap check. Both import from here and neither imports the other's helpers,
so there is no import circle. Torch-free: the standard library and numpy (imported where it is
used); onnxruntime comes in through the objects passed in.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

from e3dpsm.errors import ConfigError, DataError

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.data.sequence import EventStream
    from e3dpsm.runtime.stream import EventChunk, PoseEstimate, StreamStats

PRECISION = 4  # decimals of a joint coordinate (mm) in the CSV


def check_stream_options(args: argparse.Namespace) -> None:
    """Refuse option values the runtime cannot use, before any file is opened."""
    if args.chunk_events <= 0:
        raise ConfigError(f"--chunk-events must be positive, got {args.chunk_events}")
    if args.threads is not None and args.threads <= 0:
        raise ConfigError(f"--threads must be positive, got {args.threads}")
    if not args.max_gap_s > 0:
        raise ConfigError(f"--max-gap-s must be positive, got {args.max_gap_s}")


def check_writable_folder(folder: Path) -> None:
    """The nearest existing ancestor of `folder` must be a writable directory."""
    probe = folder.absolute()
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise DataError(f"cannot write to {folder}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise DataError(f"cannot write to {folder}: {probe} is not writable")


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


def report_head(args: argparse.Namespace, out: Path, estimator: Any, events: str | list[str]) -> dict[str, Any]:
    """The part of run's JSON report both forms write: header with the config, graph, policies.

    `estimator` is a StreamingPoseEstimator or a MultiStreamEstimator (same session, window_ms,
    frame_hw attributes)."""
    from e3dpsm.utils.env import report_header

    meta = estimator.session.meta
    config = {
        "model": str(args.model), "events": events, "out": str(out), "window_ms": estimator.window_ms,
        "threads": args.threads, "start_us": args.start_us, "chunk_events": args.chunk_events,
    }
    return {
        **report_header("run", config),
        "graph": {"variant": meta.config.get("variant"), "quantization": meta.quantization,
                  "frame_hw": list(estimator.frame_hw)},
        "pose_timestamp": "window end",
        "empty_window_policy": "stepped with an all-zero LNES frame (states decay, fusion runs)",
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
