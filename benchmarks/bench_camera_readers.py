"""Decode speed of every event-file reader on one stream (default 10 M events, 200 s, 640 x 480),
median of 3 reads, side by side in one run; each read is checked to give the same events.

AEDAT4 is read twice: by e3dpsm's own decoder (`read_events`) and, as before it, by
dv-processing's `MonoCameraRecording` followed by the same validation (`read_events` before the
decoder replaced it), so the two figures compare the same work. HDF5 is read twice too: by
`read_events` (in a forked child of the isolation helper, e3dpsm/utils/isolate.py) and in this
process (what it did before), to show what the isolation costs.

    python benchmarks/bench_camera_readers.py                    # writes benchmarks/results/camera_readers.{json,md}
    python benchmarks/bench_camera_readers.py --events 1000000 --out runs/camera_readers

The recordings (large) go to --out, kept for a look afterwards, or by default to a fresh
temporary folder removed when the run ends.

Needs the `cameras` extra (dv-processing, expelliarmus, lz4). The EVT 3.0 file is written by the
tests' spec encoder, a Python loop (about a minute for 10 M events).
"""
from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the spec EVT 3.0 encoder

from _camera_formats import encode_evt3  # noqa: E402
from e3dpsm.data.readers import read_events, read_validated_columns, write_events_h5  # noqa: E402
from e3dpsm.data.sequence import EventStream  # noqa: E402
from e3dpsm.events import validate_events  # noqa: E402
from e3dpsm.utils.env import report_header  # noqa: E402
from e3dpsm.utils.io import write_json_atomic, write_text_atomic  # noqa: E402
from e3dpsm.utils.isa import detect_isa  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
FILES = ("events.h5", "events.aedat4", "evt2.raw", "evt3.raw", "events.dat")
DV_KEY = "events.aedat4 via dv-processing"
H5_KEY = "events.h5 via h5py in this process"


def stream(n: int, seed: int = 0) -> EventStream:
    rng = np.random.default_rng(seed)
    t = rng.integers(0, 20 * n, n) + 1000  # 20 us apart on average: 1 M events = 20 s
    tab = np.unique(np.stack([t, rng.integers(0, 480, n), rng.integers(0, 2, n), rng.integers(0, 640, n)], 1), axis=0)
    return EventStream(tab[:, 3].astype(np.int32), tab[:, 1].astype(np.int32), tab[:, 0].astype(np.int64),
                       tab[:, 2].astype(np.uint8))


def write_all(s: EventStream, d: Path) -> None:
    import dv_processing as dv
    from expelliarmus import Wizard
    from expelliarmus.wizard.clib import event_t

    write_events_h5(d / "events.h5", s)
    table = np.zeros(len(s), dtype=event_t)
    table["t"], table["x"], table["y"], table["p"] = s.t_us, s.x, s.y, s.p
    Wizard(encoding="evt2").save(d / "evt2.raw", table)
    Wizard(encoding="dat").save(d / "events.dat", table)
    (d / "evt3.raw").write_bytes(encode_evt3(s, ["evt 3.0", "geometry 640x480"]))
    store = dv.EventStore()
    for t, x, y, p in zip(s.t_us.tolist(), s.x.tolist(), s.y.tolist(), s.p.tolist()):
        store.push_back(t, x, y, bool(p))
    writer = dv.io.MonoCameraWriter(str(d / "events.aedat4"), dv.io.MonoCameraWriter.EventOnlyConfig("x", (640, 480)))
    writer.writeEvents(store)
    del writer


def read_aedat4_with_dv_processing(path: Path) -> EventStream:
    """What `read_events` did on AEDAT4 before e3dpsm decoded it: dv-processing's reader, the
    columns cast, then the same validation."""
    import dv_processing as dv

    recording = dv.io.MonoCameraRecording(str(path))
    width, height = recording.getEventResolution()
    batches = []
    while (batch := recording.getNextEventBatch()) is not None:
        batches.append(batch.numpy())
    e = np.concatenate(batches)
    x, y, t, p = validate_events(e["x"].astype(np.int32), e["y"].astype(np.int32), e["timestamp"].astype(np.int64),
                                 e["polarity"].astype(np.uint8), (height, width))
    return EventStream(x=x, y=y, t_us=t, p=p, sensor_hw=(height, width))


def read_h5_in_this_process(path: Path) -> EventStream:
    """What `read_events` did on HDF5 before it read in a separate process."""
    got = read_validated_columns(path)
    return EventStream(x=got["x"], y=got["y"], t_us=got["t"], p=got["p"], sensor_hw=tuple(got["sensor_hw"]))


def median_read(read: Callable[[Path], EventStream], path: Path, want: EventStream) -> dict:
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        got = read(path)
        times.append(time.perf_counter() - t0)
        for name in ("x", "y", "t_us", "p"):
            if not np.array_equal(getattr(got, name), getattr(want, name)):
                raise SystemExit(f"{path.name}: column {name} differs from the stream written")
    med = statistics.median(times)
    return {"median_s": round(med, 4), "million_events_per_s": round(len(want) / med / 1e6, 2),
            "bytes": path.stat().st_size}


def markdown(report: dict) -> str:
    lines = [f"# Event-file readers, {report['config']['events']:,} events", "",
             f"`{report['command']}`; median of 3 reads, one process; {report['isa']['kind']} host "
             f"({report['machine'].get('cpu_model', '?')}), shared with other jobs (1-minute load average "
             f"{report['load_average'][0]:.1f} at the start, {report['load_average'][1]:.1f} at the end, on "
             f"{report['machine'].get('cpu_count', '?')} cores): compare the ratios, not the seconds with other runs.", "",
             "| file | reader | median s | M events/s | MB |", "|---|---|---:|---:|---:|"]
    for key, row in report["results"].items():
        name, _, reader = key.partition(" via ")
        lines.append(f"| {name} | {reader or 'e3dpsm (read_events)'} | {row['median_s']:.3f} | "
                     f"{row['million_events_per_s']:.1f} | "
                     f"{row['bytes'] / 1e6:.1f} |")
    ratio = report["aedat4_e3dpsm_over_dv_processing"]
    lines += ["", f"AEDAT4: e3dpsm's decoder reads {ratio:.2f}x as fast as dv-processing's `MonoCameraRecording` "
              "(the same file, the same validation after it).",
              f"HDF5: reading in a forked child of the isolation helper runs at "
              f"{report['hdf5_isolated_over_in_process']:.2f}x the speed of reading in this process."]
    return "\n".join(lines) + "\n"


def recordings_folder(out: str | None) -> contextlib.AbstractContextManager[str]:
    """Where the recordings go: `out`, created and kept, or a temporary folder removed on exit."""
    if out is None:
        return tempfile.TemporaryDirectory(prefix="e3dpsm-bench-readers-")
    Path(out).mkdir(parents=True, exist_ok=True)
    return contextlib.nullcontext(out)


def measure(out: Path, s: EventStream) -> tuple[dict, float]:
    """Median read of every file written to `out`, plus the two reference readers, and the
    load average when the reads began (after the writing, which loads the CPU itself)."""
    write_all(s, out)
    load_start = os.getloadavg()[0]
    results = {}
    for name in FILES:
        results[name] = median_read(read_events, out / name, s)
        print(name, results[name], flush=True)
    results[DV_KEY] = median_read(read_aedat4_with_dv_processing, out / "events.aedat4", s)
    print(DV_KEY, results[DV_KEY], flush=True)
    results[H5_KEY] = median_read(read_h5_in_this_process, out / "events.h5", s)
    print(H5_KEY, results[H5_KEY], flush=True)
    return results, load_start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None,
                        help="folder for the recordings (large), kept afterwards; default: a fresh "
                             "temporary folder, removed when the run ends")
    parser.add_argument("--events", type=int, default=10_000_000)
    parser.add_argument("--results", default=str(RESULTS / "camera_readers"),
                        help="report path without suffix (.json and .md are written)")
    args = parser.parse_args()
    s = stream(args.events)
    with recordings_folder(args.out) as out:
        results, load_start = measure(Path(out), s)
    report = {**report_header("bench_camera_readers", {"events": len(s)}),
              "command": "python benchmarks/bench_camera_readers.py" + (
                  f" --events {args.events}" if args.events != 10_000_000 else ""),
              "isa": detect_isa().to_dict(), "results": results,
              "load_average": [round(load_start, 2), round(os.getloadavg()[0], 2)],
              "aedat4_e3dpsm_over_dv_processing":
                  round(results[DV_KEY]["median_s"] / results["events.aedat4"]["median_s"], 2),
              "hdf5_isolated_over_in_process": round(results[H5_KEY]["median_s"] / results["events.h5"]["median_s"], 2)}
    write_json_atomic(f"{args.results}.json", report)
    write_text_atomic(f"{args.results}.md", markdown(report))
    print(f"AEDAT4: {report['aedat4_e3dpsm_over_dv_processing']}x dv-processing -> {args.results}.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
