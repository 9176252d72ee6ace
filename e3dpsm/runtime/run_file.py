"""`e3dpsm run`'s one-file form: an event file (.h5/.hdf5/.npz, or a camera recording) through
the streaming runtime, poses to CSV.

Output: the request's `out` CSV with columns t_us (window end) then <joint>_x/_y/_z in mm for
the joints named in the graph's metadata, and `<stem>.report.json` beside it, optionally a
video (`render`). Everything is written under temporary names and renamed only when the
whole stream ran. Torch-free (numpy, onnxruntime, the csv module): the form a device runs.
"""
from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Iterator

from e3dpsm.runtime.run_command import RunResult
from e3dpsm.runtime.run_output import (
    check_gaps, event_chunks, no_window_error, report_path, stream_report, write_pose_csv,
)

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.runtime.render_stream import StreamRender
    from e3dpsm.runtime.run_command import RunRequest
    from e3dpsm.runtime.stream import EventChunk, PoseEstimate, StreamingPoseEstimator


def run_file(request: RunRequest) -> RunResult:
    """The one-file form; `request.out` already checked (run_command.run_poses)."""
    from e3dpsm.data.readers import read_events
    from e3dpsm.runtime import StreamingPoseEstimator
    from e3dpsm.runtime.stepping import open_stepper
    from e3dpsm.utils.io import atomic_path, write_json_atomic

    events, out = request.events[0], request.out
    _check_render(request)
    session = open_stepper(request.model, threads=request.threads)  # a bad graph fails before reading events
    # The file's own sensor size (attributes or event_meta.json) wins over the graph's default.
    stream = read_events(events)
    estimator = StreamingPoseEstimator(
        session, window_ms=request.window_ms, start_us=request.start_us, sensor_hw=stream.sensor_hw,
        keep_frames=request.render is not None,
    )
    check_gaps(stream.t_us, request.max_gap_s, estimator.window_ms, events)
    video = _stream_render(request, estimator)
    chunks = event_chunks(stream, request.chunk_events)
    if request.progress:
        chunks = _with_progress(chunks, len(stream))

    with atomic_path(out, suffix=".csv") as tmp_csv, atomic_path(report_path(out), suffix=".json") as tmp_report, \
            video or contextlib.nullcontext():
        poses = estimator.run(chunks)
        write_pose_csv(tmp_csv, estimator.joints, poses if video is None else _drawn(poses, video))
        if estimator.stats.windows == 0:  # documented choice: an error, not an empty CSV
            raise no_window_error(events, stream, estimator.window_ms, estimator.stats)
        report = stream_report(request, estimator, events, events_in_file=len(stream))
        write_json_atomic(tmp_report, report)
    return RunResult(report, _summary(report, out, video))


def _check_render(request: RunRequest) -> None:
    """A missing .mp4 encoder or an existing video is reported before the stream runs."""
    if request.render is None:
        return
    from e3dpsm.runtime.render import check_render_path
    from e3dpsm.utils.io import check_writable_folder

    check_render_path(request.render, force=request.force, max_frames=request.render_max_frames)
    check_writable_folder(Path(request.render).parent)


def _stream_render(request: RunRequest, estimator: StreamingPoseEstimator) -> StreamRender | None:
    if request.render is None:
        return None
    from e3dpsm.runtime.render_stream import StreamRender

    return StreamRender(request.render, request.events[0], estimator.window_us, estimator.sensor_hw,
                        max_frames=request.render_max_frames, force=request.force)


def _drawn(poses: Iterable[PoseEstimate], video: StreamRender) -> Iterator[PoseEstimate]:
    for pose in poses:
        video.add(pose)
        yield pose


def _summary(report: dict, out: Path, video: StreamRender | None) -> tuple[str, ...]:
    lines = [
        f"{report['windows']} poses ({report['empty_windows']} empty windows, {report['events']} events) at "
        f"{report['mean_step_ms']:.2f} ms/step + {report['overhead_ms']:.2f} ms runtime overhead -> {out}"
    ]
    if video is not None:  # closed by now: its summary counts every frame written
        done = video.video.summary()
        first = f" (the first {done.frames} of {done.poses_seen} poses)" if done.frames < done.poses_seen else ""
        lines.append(f"render: {done.frames} frames{first}, {done.frames_with_ground_truth} with ground truth "
                     f"-> {done.path}")
    return tuple(lines)


def _with_progress(chunks: Iterator[EventChunk], total_events: int) -> Iterator[EventChunk]:
    try:
        from tqdm import tqdm
    except ImportError:  # devices without tqdm run without a bar
        yield from chunks
        return
    with tqdm(total=total_events, unit="ev", unit_scale=True, desc="run", file=sys.stderr) as bar:
        for chunk in chunks:
            yield chunk
            bar.update(len(chunk[2]))
