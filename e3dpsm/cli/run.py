"""`e3dpsm run`: drive an exported step graph over an event file, poses to CSV.

Options only; the body is e3dpsm.runtime.run_command (one file, several files or a live
dv:// source; docs/runtimes.md). Torch-free, like the runtime: the command a device runs.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from e3dpsm.cli._common import add_force, add_threads
from e3dpsm.runtime.run_command import DEFAULT_CHUNK_EVENTS, LIVE_TIMEOUT_S, MAX_GAP_S, RunRequest, run_poses


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
    parser.add_argument("--live-timeout-s", type=float, default=LIVE_TIMEOUT_S,
                        help="dv:// source: connect timeout, and how long a silent stream counts as stopped "
                        f"(default {LIVE_TIMEOUT_S:g})")
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    request = RunRequest(
        model=args.model, events=tuple(args.events), out=Path(args.out), window_ms=args.window_ms,
        threads=args.threads, start_us=args.start_us, chunk_events=args.chunk_events, max_gap_s=args.max_gap_s,
        force=args.force, progress=not args.no_progress and sys.stderr.isatty(), render=args.render,
        render_max_frames=args.render_max_frames, max_seconds=args.max_seconds, live_timeout_s=args.live_timeout_s,
    )
    for line in run_poses(request).summary:
        print(line)
    return 0
