"""`e3dpsm run`'s many-file form: several event files as independent streams through one
session (e3dpsm.runtime.MultiStreamEstimator), one CSV per file.

Each file is one stream with its own window grid and states; the streams' chunks are pushed
together, so the windows they complete share batched session calls. The request's `out` is a
folder: one CSV per file, named by `stream_names` (same columns as the one-file form), and one
`run.report.json` recording which file went to which CSV. Everything is written under
temporary names and renamed only once every stream ran; a file that yields no complete window
fails the whole run, as in the one-file form. Torch-free, like the one-file form.
"""
from __future__ import annotations

import contextlib
import csv
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

from e3dpsm.errors import ConfigError
from e3dpsm.runtime.run_command import RunResult
from e3dpsm.runtime.run_output import check_gaps, event_chunks, no_window_error, pose_columns, pose_row, report_head

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.runtime.run_command import RunRequest

NAME_JOIN = "__"  # between the folder names that tell two sequences apart: a__seq_0000.csv
REPORT_NAME = "run.report.json"


def run_many(request: RunRequest) -> RunResult:
    """The many-file form; the request's options already checked (RunRequest)."""
    from e3dpsm.data.readers import read_events
    from e3dpsm.runtime import MultiStreamEstimator
    from e3dpsm.runtime.stepping import open_stepper
    from e3dpsm.utils.io import atomic_path, write_json_atomic

    out = request.out
    sources, targets = _outputs(request)
    session = open_stepper(request.model, threads=request.threads)  # a bad graph fails before reading events
    streams = {name: read_events(path) for name, path in sources.items()}
    estimator = MultiStreamEstimator(session, window_ms=request.window_ms)
    for name, stream in streams.items():  # the file's own sensor size wins over the graph's default
        estimator.add_stream(name, start_us=request.start_us, sensor_hw=stream.sensor_hw)
        check_gaps(stream.t_us, request.max_gap_s, estimator.window_ms, sources[name])

    with contextlib.ExitStack() as stack:
        stack.enter_context(_removed_on_failure_if_new(out))  # entered first: leaves after the temporaries
        tmp_report = stack.enter_context(atomic_path(out / REPORT_NAME, suffix=".json"))
        writers = {}
        for name, target in targets.items():
            handle = stack.enter_context(open(stack.enter_context(atomic_path(target, suffix=".csv")), "w",
                                              newline="", encoding="utf-8"))
            writers[name] = csv.writer(handle)
            writers[name].writerow(pose_columns(estimator.joints))
        _run_streams(estimator, {name: event_chunks(stream, request.chunk_events)
                                 for name, stream in streams.items()}, writers)
        for name, stream in streams.items():  # documented choice: an error, not an empty CSV
            stats = estimator.stream_stats(name)
            if stats.windows == 0:  # every stream has the estimator's window
                raise no_window_error(sources[name], stream, estimator.window_ms, stats)
        report = _report(request, estimator, streams, sources, targets)
        write_json_atomic(tmp_report, report)
    totals = report["totals"]
    return RunResult(report, (
        f"{len(streams)} streams, {totals['rows_stepped']} poses in {totals['session_calls']} batched steps "
        f"(mean batch {totals['mean_batch']:.2f}) at {totals['mean_step_ms_per_pose']:.2f} ms/pose + "
        f"{totals['mean_overhead_ms_per_pose']:.2f} ms runtime overhead -> {out}",))


def _outputs(request: RunRequest) -> tuple[dict[str, str], dict[str, Path]]:
    """Stream name -> event file and stream name -> CSV, refusing outputs it must not replace."""
    from e3dpsm.errors import DataError, OutputExistsError
    from e3dpsm.utils.io import check_writable_folder

    out = request.out
    if out.exists() and not out.is_dir():
        raise DataError(f"--out {out} is a file; with several --events files it names a folder of CSVs")
    sources = dict(zip(stream_names(list(request.events)), request.events))
    targets = {name: out / f"{name}.csv" for name in sources}
    existing = [str(p) for p in [*targets.values(), out / REPORT_NAME] if p.exists()]
    if existing and not request.force:
        raise OutputExistsError(f"{existing[0]} exists; pass --force to replace it")
    check_writable_folder(out)
    return sources, targets
def stream_names(events: list[str]) -> list[str]:
    """One name per event file (its CSV is `<name>.csv`), saying what tells the files apart.

    Each path is read as its folder names then its file stem (made absolute, not resolving
    links, so `..` never shows up). The run of trailing parts that every path shares is
    dropped (`events` when every file is `<sequence>/events.h5`), keeping at least one part.
    Each file is then named by the shortest trailing run of what is left that does not end
    any other path, its parts joined with `__`; a path whose whole rest ends another one is
    named by that whole rest. So: `seq_0000/events.h5 seq_0001/events.h5` -> `seq_0000`,
    `seq_0001`; `walk.h5 sit.h5` -> `walk`, `sit`; `a/seq_0000/events.h5 b/seq_0000/events.h5
    a/seq_0001/events.h5` -> `a__seq_0000`, `b__seq_0000`, `seq_0001`.

    Refused with ConfigError: the same file given twice, two paths that differ only in their
    extension (`x/events.h5`, `x/events.npz`), and names that still clash once joined or
    compared ignoring letter case (as on case-insensitive file systems).
    """
    seen: dict[Path, str] = {}
    for path in events:
        real = Path(path).resolve()
        if real in seen:
            raise ConfigError(f"--events {path} is the same file as {seen[real]}; give each event file once")
        seen[real] = path
    parts = [(*Path(os.path.abspath(path)).parent.parts[1:], Path(path).stem) for path in events]
    first: dict[tuple[str, ...], str] = {}
    for path, key in zip(events, parts):
        if key in first:  # only the extension differs: no folder or stem is left to name the CSVs by
            raise ConfigError(f"--events {first[key]} and {path} differ only in their extension; each CSV is "
                              "named by folder and file names, so rename or link one of them")
        first[key] = path
    shared = 0  # trailing parts every path has, never all of the shortest path's parts
    while shared < min(map(len, parts)) - 1 and len({p[len(p) - 1 - shared] for p in parts}) == 1:
        shared += 1
    rests = [p[:len(p) - shared] for p in parts]
    names = []
    for i, rest in enumerate(rests):
        others = [other for j, other in enumerate(rests) if j != i]
        length = next((k for k in range(1, len(rest) + 1) if all(other[-k:] != rest[-k:] for other in others)),
                      len(rest))
        names.append(NAME_JOIN.join(rest[-length:]))
    clashes: dict[str, str] = {}
    for name, path in zip(names, events):
        if name.casefold() in clashes:
            raise ConfigError(
                f"--events {clashes[name.casefold()]} and {path} would both write {name}.csv (CSV names are "
                "compared ignoring letter case, for case-insensitive file systems); rename or link one of them"
            )
        clashes[name.casefold()] = path
    return names


@contextlib.contextmanager
def _removed_on_failure_if_new(folder: Path) -> Iterator[None]:
    """A failed run leaves no empty --out folder that it created itself."""
    new = not folder.exists()
    try:
        yield
    except BaseException:
        if new:
            with contextlib.suppress(OSError):  # not empty (someone else wrote there): keep it
                folder.rmdir()
        raise


def _run_streams(estimator: Any, chunk_iterators: dict[str, Any], writers: dict[str, Any]) -> None:
    """Push one chunk of every stream per round (their windows batch together), then finish each."""
    active = dict(chunk_iterators)
    while active:
        batch, ended = {}, []
        for name, chunks in active.items():
            chunk = next(chunks, None)
            if chunk is None:
                ended.append(name)
            else:
                batch[name] = chunk
        for name in ended:
            del active[name]
        results = [estimator.push_many(batch)] if batch else []
        if ended:
            results.append(estimator.finish_many(ended))
        for poses_by_stream in results:
            for name, poses in poses_by_stream.items():
                for pose in poses:
                    writers[name].writerow(pose_row(pose))


def _report(request: RunRequest, estimator: Any, streams: dict, sources: dict[str, str],
            targets: dict[str, Path]) -> dict:
    per_stream = {}
    for name, stream in streams.items():
        stats = estimator.stream_stats(name).to_dict()
        per_stream[name] = {
            "events_file": sources[name], "csv": str(targets[name]),
            "sensor_hw": list(stream.sensor_hw), "first_window_start_us": estimator.first_window_start_us(name),
            "events_in_file": len(stream), **stats,
        }
    return {
        **report_head(request, request.out, estimator, list(request.events)),
        "batching": "the streams' complete windows share batched session calls (one row per stream)",
        "csv_naming": "each CSV is named by the shortest end of its event file's path (folders, stem; joined with "
                      f"{NAME_JOIN!r}) that tells it apart from the other files, after the end they all share",
        "streams": per_stream,
        "totals": estimator.stats.to_dict(),
    }
