"""`e3dpsm run`: drive an exported step graph over an event file, poses to CSV.

Torch-free (numpy, onnxruntime, the csv module): the command a device runs.

Output: `--out poses.csv` with columns t_us (window end) then <joint>_x/_y/_z in mm for the
joints named in the graph's metadata, and `poses.report.json` beside it. Both are written
under temporary names and renamed only when the whole stream ran, so a failure leaves
nothing behind. A stream that yields no complete window (no events, or shorter than one
window) is an error rather than an empty CSV: a pipeline waiting for poses should stop.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

from e3dpsm.cli._common import add_force, add_threads
from e3dpsm.cli._run_common import (
    check_gaps, check_stream_options, check_writable_folder, event_chunks, no_window_error, pose_columns, pose_row,
    report_head,
)

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.runtime import StreamingPoseEstimator
    from e3dpsm.runtime.stream import EventChunk

DEFAULT_CHUNK_EVENTS = 100_000
MAX_GAP_S = 60.0


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "run",
        help="stream an event file through an exported step graph and write timestamped poses (CSV)",
        description="Read an event file (.h5/.hdf5/.npz, or a camera recording .aedat4/.raw/.dat; docs/cameras.md) "
        "or a live dv://HOST:PORT stream, feed it in chunks to the streaming runtime "
        "(T-ms windows, LNES frames, recurrent states carried; numpy + onnxruntime only) and write one "
        "pose per window, timestamped at the window end, in millimetres. Empty windows are stepped with "
        "an all-zero frame. A JSON report is written next to the CSV.",
    )
    parser.add_argument("--model", required=True, help="step graph written by `e3dpsm export` (or quantize)")
    parser.add_argument("--events", required=True, nargs="+",
                        help="event file: .h5/.hdf5 (EE3D layout), .npz (x, y, t, p), .aedat4, Prophesee .raw "
                        "(EVT 2.0/3.0) or .dat; several files are run as independent streams batched through one "
                        "session; or one live dv-processing stream dv://HOST:PORT (docs/cameras.md)")
    parser.add_argument("--out", required=True,
                        help="CSV of poses to write (report: <stem>.report.json); with several --events files a "
                        "folder getting one CSV per file and one run.report.json. Each CSV is named by the "
                        "shortest end of its file's path that tells it apart from the others, after dropping the "
                        "end all files share: seq_0000/events.h5 seq_0001/events.h5 -> seq_0000.csv seq_0001.csv, "
                        "a.h5 b.h5 -> a.csv b.csv, deeper clashes join folders with __ (a__seq_0000.csv)")
    parser.add_argument("--window-ms", type=float, default=None,
                        help="window length T in ms (default: the graph's training window, 20)")
    add_threads(parser, "onnxruntime intra-op threads")
    parser.add_argument("--start-us", type=int, default=None,
                        help="start of the first window in us (default: the first event); earlier events are skipped")
    parser.add_argument("--chunk-events", type=int, default=DEFAULT_CHUNK_EVENTS,
                        help=f"events handed to the runtime per chunk (default {DEFAULT_CHUNK_EVENTS})")
    add_force(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--render", default=None, metavar="PATH",
                        help="also write a video (.gif; .mp4 with imageio + imageio-ffmpeg) of each window's LNES "
                        "frame with the predicted skeleton (gold) and the ground truth (green) when the events' "
                        "folder has it (gt.npz or the EE3D pickle)")
    parser.add_argument("--render-max-frames", type=int, default=None, metavar="N",
                        help="render only the first N poses (the CSV still holds every pose)")
    parser.add_argument("--max-seconds", type=float, default=None,
                        help="dv:// source: stop after this many seconds of wall time (default: until the publisher stops)")
    parser.add_argument("--max-gap-s", type=float, default=MAX_GAP_S,
                        help="refuse a silence longer than this between two events (default "
                        f"{MAX_GAP_S:g} s): every empty window is stepped, so a corrupted timestamp would keep "
                        "run stepping for hours; an event camera is never silent that long")
    parser.add_argument("--live-timeout-s", type=float, default=5.0,
                        help="dv:// source: connect timeout, and how long a silent stream counts as stopped (default 5)")
    parser.set_defaults(func=run)
    return parser


def report_path(out: Path) -> Path:
    return out.with_name(out.stem + ".report.json")


def run(args: argparse.Namespace) -> int:
    from e3dpsm.data.readers import read_events
    from e3dpsm.errors import ConfigError, DataError, OutputExistsError
    from e3dpsm.runtime import StreamingPoseEstimator
    from e3dpsm.runtime.stepping import open_stepper
    from e3dpsm.utils.io import atomic_path, write_json_atomic

    # The one --render check for both forms: the many-file form never sees --render.
    if len(args.events) > 1 and (args.render is not None or args.render_max_frames is not None):
        raise ConfigError("--render draws one stream: pass a single --events file")
    check_stream_options(args)
    from e3dpsm.data.live import is_live_url

    if len(args.events) > 1 and any(is_live_url(e) for e in args.events):
        raise ConfigError("a live dv:// source runs alone: pass it as the only --events")
    if len(args.events) > 1:  # several streams, one session: e3dpsm/cli/_run_many.py
        from e3dpsm.cli._run_many import run_many

        return run_many(args)
    args.events = args.events[0]  # one file: exactly the single-stream command below
    out = Path(args.out)
    if out.is_dir():
        raise DataError(f"--out {out} is a folder; expected a CSV file path")
    if out.exists() and not args.force:
        raise OutputExistsError(f"{out} exists; pass --force to replace it")
    check_writable_folder(out.parent)  # fail before minutes of inference, not after
    if is_live_url(args.events):
        from e3dpsm.cli._run_live import run_live

        return run_live(args, out, report_path(out))
    if args.render is None and args.render_max_frames is not None:
        raise ConfigError("--render-max-frames needs --render PATH")
    if args.render is not None:  # a missing .mp4 encoder is reported before the stream runs
        from e3dpsm.runtime.render import check_render_path

        check_render_path(args.render, force=args.force, max_frames=args.render_max_frames)
        check_writable_folder(Path(args.render).parent)

    session = open_stepper(args.model, threads=args.threads)  # a bad graph fails before reading events
    # The file's own sensor size (attributes or event_meta.json) wins over the graph's default.
    stream = read_events(args.events)
    estimator = StreamingPoseEstimator(
        session, window_ms=args.window_ms, start_us=args.start_us, sensor_hw=stream.sensor_hw,
        keep_frames=args.render is not None,
    )
    check_gaps(stream.t_us, args.max_gap_s, estimator.window_ms, args.events)
    video = _stream_render(args, estimator)
    chunks = event_chunks(stream, args.chunk_events)
    if not args.no_progress and sys.stderr.isatty():
        chunks = _with_progress(chunks, len(stream))

    # Rows go to the temporary CSV as they come (memory stays flat on long recordings); both
    # files appear under their names only once the whole stream ran.
    with atomic_path(out, suffix=".csv") as tmp_csv, atomic_path(report_path(out), suffix=".json") as tmp_report, \
            video or contextlib.nullcontext():
        with open(tmp_csv, "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(pose_columns(estimator.joints))
            for pose in estimator.run(chunks):
                writer.writerow(pose_row(pose))
                if video is not None:
                    video.add(pose)
        if estimator.stats.windows == 0:  # documented choice: an error, not an empty CSV
            raise no_window_error(args.events, stream, estimator.window_ms, estimator.stats)
        report = _report(args, out, estimator, len(stream))
        write_json_atomic(tmp_report, report)
    print(
        f"{report['windows']} poses ({report['empty_windows']} empty windows, {report['events']} events) at "
        f"{report['mean_step_ms']:.2f} ms/step + {report['overhead_ms']:.2f} ms runtime overhead -> {out}"
    )
    if video is not None:
        done = video.video.summary()
        first = f" (the first {done.frames} of {done.poses_seen} poses)" if done.frames < done.poses_seen else ""
        print(f"render: {done.frames} frames{first}, {done.frames_with_ground_truth} with ground truth -> {done.path}")
    return 0


def _stream_render(args: argparse.Namespace, estimator: StreamingPoseEstimator):  # -> StreamRender | None
    if args.render is None:
        return None
    from e3dpsm.runtime.render_stream import StreamRender

    return StreamRender(args.render, args.events, estimator.window_us, estimator.sensor_hw,
                        max_frames=args.render_max_frames, force=args.force)


def _report(args: argparse.Namespace, out: Path, estimator: StreamingPoseEstimator, events_in_file: int) -> dict:
    summary = estimator.stats.to_dict()
    return {
        **report_head(args, out, estimator, str(args.events)),
        "sensor_hw": list(estimator.sensor_hw),
        "first_window_start_us": estimator.first_window_start_us,
        "events_in_file": events_in_file,
        **summary,
        "overhead_ms": summary["mean_overhead_ms"],  # per window: validation, windowing, LNES, feeds
    }


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

