"""`e3dpsm run --events dv://HOST:PORT`: poses from a live dv-processing event stream until the
publisher stops or `--max-seconds` of wall time pass. Same CSV and report as a file, written
under temporary names and renamed at the end; the report adds `live` (why it stopped).
Torch-free, like run.py.
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

from e3dpsm.cli._run_common import check_gaps, pose_columns, pose_row, report_head

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.data.live import LiveEventSource
    from e3dpsm.runtime.stream import EventChunk


def run_live(args: argparse.Namespace, out: Path, report_path: Path) -> int:
    from e3dpsm.data.live import open_live_source
    from e3dpsm.errors import ConfigError, DataError
    from e3dpsm.runtime import StreamingPoseEstimator
    from e3dpsm.runtime.stepping import open_stepper
    from e3dpsm.utils.io import atomic_path, write_json_atomic

    if args.render is not None:
        raise ConfigError("--render draws a recording; it is not available for a live dv:// source")
    if args.max_seconds is not None and args.max_seconds <= 0:
        raise ConfigError(f"--max-seconds must be positive, got {args.max_seconds}")
    session = open_stepper(args.model, threads=args.threads)
    with open_live_source(args.events, timeout_s=args.live_timeout_s) as source:
        estimator = StreamingPoseEstimator(session, window_ms=args.window_ms, start_us=args.start_us,
                                           sensor_hw=source.sensor_hw)
        chunks = _chunks(source, args.max_seconds, args.max_gap_s, estimator.window_ms)
        with atomic_path(out, suffix=".csv") as tmp_csv, atomic_path(report_path, suffix=".json") as tmp_report:
            with open(tmp_csv, "w", newline="", encoding="utf-8") as fh:
                writer = csv.writer(fh)
                writer.writerow(pose_columns(estimator.joints))
                for pose in estimator.run(chunks):
                    writer.writerow(pose_row(pose))
            reason = source.stopped_reason or f"--max-seconds {args.max_seconds:g} reached"
            if estimator.stats.windows == 0:
                raise DataError(f"{args.events}: no complete {estimator.window_ms:g} ms window before the stream "
                                f"ended ({reason}); nothing to estimate")
            summary = estimator.stats.to_dict()
            report = {
                **report_head(args, out, estimator, str(args.events)),
                "sensor_hw": list(estimator.sensor_hw),
                "first_window_start_us": estimator.first_window_start_us,
                "live": {"url": args.events, "events_received": source.events, "stopped": reason,
                         "max_seconds": args.max_seconds},
                **summary,
                "overhead_ms": summary["mean_overhead_ms"],
            }
            write_json_atomic(tmp_report, report)
    print(f"{report['windows']} poses from {args.events} ({source.events} events; {reason}) -> {out}")
    return 0


def _chunks(source: LiveEventSource, max_seconds: float | None, max_gap_s: float,
            window_ms: float) -> Iterator[EventChunk]:
    deadline = None if max_seconds is None else time.monotonic() + max_seconds
    last_us = None
    for chunk in source:
        check_gaps(chunk.t_us, max_gap_s, window_ms, source.url, previous_us=last_us)
        last_us = int(chunk.t_us[-1]) if len(chunk) else last_us
        yield chunk.x, chunk.y, chunk.t_us, chunk.p
        if deadline is not None and time.monotonic() >= deadline:
            return
