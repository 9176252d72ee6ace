"""Decode speed of every event-file reader on one stream (default 1 M events, 20 s, 640 x 480),
median of 3 reads, side by side in one run; each read is checked to give the same events.

    python benchmarks/bench_camera_readers.py --out /tmp/camera_readers   # writes report.json there

Needs the `cameras` extra (dv-processing) and expelliarmus (the EVT 2.0 / DAT writer).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the spec EVT 3.0 encoder

from _camera_formats import encode_evt3  # noqa: E402
from e3dpsm.data.readers import read_events, write_events_h5  # noqa: E402
from e3dpsm.data.sequence import EventStream  # noqa: E402
from e3dpsm.utils.env import report_header  # noqa: E402
from e3dpsm.utils.io import write_json_atomic  # noqa: E402


def stream(n: int, seed: int = 0) -> EventStream:
    rng = np.random.default_rng(seed)
    t = rng.integers(0, 20_000_000, n) + 1000
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="/tmp/camera_readers")
    parser.add_argument("--events", type=int, default=1_000_000)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    s = stream(args.events)
    write_all(s, out)
    results = {}
    for name in ("events.h5", "events.aedat4", "evt2.raw", "evt3.raw", "events.dat"):
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            got = read_events(out / name)
            times.append(time.perf_counter() - t0)
            assert np.array_equal(got.t_us, s.t_us) and np.array_equal(got.x, s.x) and np.array_equal(got.p, s.p)
        med = statistics.median(times)
        results[name] = {"median_s": round(med, 4), "million_events_per_s": round(len(s) / med / 1e6, 2),
                         "bytes": (out / name).stat().st_size}
        print(name, results[name])
    write_json_atomic(out / "report.json", {**report_header("bench_camera_readers", {"events": len(s)}),
                                            "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
