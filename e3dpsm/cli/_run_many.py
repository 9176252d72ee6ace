"""`e3dpsm run --events a.h5 b.h5 ... --out DIR`: several event files as independent streams
through one session (e3dpsm.runtime.MultiStreamEstimator), one CSV per file.

Each file is one stream with its own window grid and states; the streams' chunks are pushed
together, so the windows they complete share batched session calls. `--out` is a folder:
`<event file stem>.csv` per file (same columns as the one-file form) and one
`run.report.json`. Everything is written under temporary names and renamed only once every
stream ran; a file that yields no complete window fails the whole run, as in the one-file form.
Torch-free, like the one-file command.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
from pathlib import Path
from types import SimpleNamespace
from typing import Any

REPORT_NAME = "run.report.json"


def run_many(args: argparse.Namespace) -> int:
    from e3dpsm.cli.run import _check_writable_folder, _chunks, _no_window_error
    from e3dpsm.data.readers import read_events
    from e3dpsm.errors import ConfigError, DataError, OutputExistsError
    from e3dpsm.runtime import MultiStreamEstimator, StepSession
    from e3dpsm.utils.io import atomic_path, write_json_atomic

    if args.chunk_events <= 0:
        raise ConfigError(f"--chunk-events must be positive, got {args.chunk_events}")
    if args.threads is not None and args.threads <= 0:
        raise ConfigError(f"--threads must be positive, got {args.threads}")
    if getattr(args, "render", None) is not None:
        raise ConfigError("--render works with one --events file; run the files one by one to render them")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise DataError(f"--out {out} is a file; with several --events files it names a folder of CSVs")
    targets = _csv_targets(args.events, out)
    existing = [str(p) for p in [*targets.values(), out / REPORT_NAME] if p.exists()]
    if existing and not args.force:
        raise OutputExistsError(f"{existing[0]} exists; pass --force to replace it")
    _check_writable_folder(out)

    session = StepSession(args.model, threads=args.threads)  # a bad graph fails before reading events
    streams = {stem: read_events(path) for stem, path in zip(targets, args.events)}
    estimator = MultiStreamEstimator(session, window_ms=args.window_ms)
    for stem, stream in streams.items():  # the file's own sensor size wins over the graph's default
        estimator.add_stream(stem, start_us=args.start_us, sensor_hw=stream.sensor_hw)
    columns = ["t_us", *(f"{joint}_{axis}" for joint in estimator.joints for axis in "xyz")]

    with contextlib.ExitStack() as stack:
        tmp_report = stack.enter_context(atomic_path(out / REPORT_NAME, suffix=".json"))
        writers = {}
        for stem, target in targets.items():
            handle = stack.enter_context(open(stack.enter_context(atomic_path(target, suffix=".csv")), "w",
                                              newline="", encoding="utf-8"))
            writers[stem] = csv.writer(handle)
            writers[stem].writerow(columns)
        _run_streams(estimator, {stem: _chunks(stream, args.chunk_events) for stem, stream in streams.items()},
                     writers)
        for stem, stream in streams.items():  # documented choice: an error, not an empty CSV
            stats = estimator.stream_stats(stem)
            if stats.windows == 0:
                view = SimpleNamespace(window_ms=estimator.window_ms, stats=stats)  # every stream has the default window
                raise _no_window_error(_source(args.events, targets, stem), stream, view)
        report = _report(args, out, estimator, streams, targets)
        write_json_atomic(tmp_report, report)
    totals = report["totals"]
    print(
        f"{len(streams)} streams, {totals['rows_stepped']} poses in {totals['session_calls']} batched steps "
        f"(mean batch {totals['mean_batch']:.2f}) at {totals['mean_step_ms_per_pose']:.2f} ms/pose + "
        f"{totals['mean_overhead_ms_per_pose']:.2f} ms runtime overhead -> {out}"
    )
    return 0


def _csv_targets(events: list[str], out: Path) -> dict[str, Path]:
    """Stream name (the event file stem) -> CSV path; two files with one stem are refused."""
    from e3dpsm.errors import ConfigError

    targets: dict[str, Path] = {}
    for path in events:
        stem = Path(path).stem
        if stem in targets:
            raise ConfigError(
                f"two --events files have the same name {stem!r} ({path} and another); each CSV is named "
                "after its event file, so rename or link one of them"
            )
        targets[stem] = out / f"{stem}.csv"
    return targets


def _source(events: list[str], targets: dict[str, Path], stem: str) -> str:
    """The event file a stream came from."""
    return events[list(targets).index(stem)]


def _run_streams(estimator: Any, chunk_iterators: dict[str, Any], writers: dict[str, Any]) -> None:
    """Push one chunk of every stream per round (their windows batch together), then finish each."""
    active = dict(chunk_iterators)
    while active:
        batch, ended = {}, []
        for stem, chunks in active.items():
            chunk = next(chunks, None)
            if chunk is None:
                ended.append(stem)
            else:
                batch[stem] = chunk
        for stem in ended:
            del active[stem]
        results = [estimator.push_many(batch)] if batch else []
        if ended:
            results.append(estimator.finish_many(ended))
        for poses_by_stream in results:
            for stem, poses in poses_by_stream.items():
                for pose in poses:
                    writers[stem].writerow([pose.t_us, *(f"{v:.4f}" for v in pose.pose.reshape(-1).tolist())])


def _report(args: argparse.Namespace, out: Path, estimator: Any, streams: dict, targets: dict[str, Path]) -> dict:
    from e3dpsm.utils.env import report_header

    meta = estimator.session.meta
    config = {
        "model": str(args.model), "events": [str(e) for e in args.events], "out": str(out),
        "window_ms": estimator.window_ms, "threads": args.threads, "start_us": args.start_us,
        "chunk_events": args.chunk_events,
    }
    per_stream = {}
    for stem, stream in streams.items():
        stats = estimator.stream_stats(stem).to_dict()
        per_stream[stem] = {
            "events_file": _source(args.events, targets, stem), "csv": str(targets[stem]),
            "sensor_hw": list(stream.sensor_hw), "first_window_start_us": estimator.first_window_start_us(stem),
            "events_in_file": len(stream), **stats,
        }
    return {
        **report_header("run", config),
        "graph": {"variant": meta.config.get("variant"), "quantization": meta.quantization,
                  "frame_hw": list(estimator.frame_hw)},
        "pose_timestamp": "window end",
        "empty_window_policy": "stepped with an all-zero LNES frame (states decay, fusion runs)",
        "batching": "the streams' complete windows share batched session calls (one row per stream)",
        "streams": per_stream,
        "totals": estimator.stats.to_dict(),
    }
