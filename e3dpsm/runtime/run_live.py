"""`e3dpsm run`'s live form: poses from a dv-processing event stream (dv://HOST:PORT) until the
publisher stops or `max_seconds` of wall time pass. Same CSV and report as a file, written
under temporary names and renamed at the end; the report adds `live` (why it stopped).
Torch-free, like the one-file form.
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING, Callable, Iterator

from e3dpsm.runtime.run_command import RunResult
from e3dpsm.runtime.run_output import check_gaps, report_path, stream_report, write_pose_csv

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.data.live import LiveEventSource
    from e3dpsm.runtime.run_command import RunRequest
    from e3dpsm.runtime.stream import EventChunk


def run_live(request: RunRequest) -> RunResult:
    """The live form; `request.out` already checked (run_command.run_poses)."""
    from e3dpsm.data.live import open_live_source
    from e3dpsm.errors import DataError
    from e3dpsm.runtime import StreamingPoseEstimator
    from e3dpsm.runtime.stepping import open_stepper
    from e3dpsm.utils.io import atomic_path, write_json_atomic

    url, out = request.events[0], request.out
    session = open_stepper(request.model, threads=request.threads)
    with open_live_source(url, timeout_s=request.live_timeout_s) as source:
        estimator = StreamingPoseEstimator(session, window_ms=request.window_ms, start_us=request.start_us,
                                           sensor_hw=source.sensor_hw)
        chunks = _chunks(source, request.max_seconds, request.max_gap_s, estimator.window_ms)
        with atomic_path(out, suffix=".csv") as tmp_csv, atomic_path(report_path(out), suffix=".json") as tmp_report:
            write_pose_csv(tmp_csv, estimator.joints, estimator.run(chunks))
            reason = source.stopped_reason or f"--max-seconds {request.max_seconds:g} reached"
            if estimator.stats.windows == 0:
                raise DataError(f"{url}: no complete {estimator.window_ms:g} ms window before the stream "
                                f"ended ({reason}); nothing to estimate")
            live = {"url": url, "events_received": source.events, "stopped": reason,
                    "max_seconds": request.max_seconds}
            report = stream_report(request, estimator, url, live=live)
            write_json_atomic(tmp_report, report)
    return RunResult(report, (f"{report['windows']} poses from {url} ({source.events} events; {reason}) -> {out}",))


def _chunks(source: LiveEventSource, max_seconds: float | None, max_gap_s: float, window_ms: float,
            clock: Callable[[], float] = time.monotonic) -> Iterator[EventChunk]:
    deadline = None if max_seconds is None else clock() + max_seconds
    last_us = None
    for chunk in source:
        check_gaps(chunk.t_us, max_gap_s, window_ms, source.url, previous_us=last_us)
        last_us = int(chunk.t_us[-1]) if len(chunk) else last_us
        yield chunk.x, chunk.y, chunk.t_us, chunk.p
        if deadline is not None and clock() >= deadline:
            return
