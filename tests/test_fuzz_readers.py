"""Fuzzing the event readers: damaged copies of files that independent writers produced
(expelliarmus: EVT 2.0, DAT; dv-processing: AEDAT4 with LZ4, Zstd and no compression; h5py:
HDF5 in the EE3D layout and as separate datasets; numpy: .npz; the tests' spec encoder: EVT
3.0, since expelliarmus' EVT 3.0 writer is wrong, docs/cameras.md). Each input is read by
`read_events` in a child process (tests/_bounded.py) under a time bound; it must end with
events or one DataError line. A hang, a crash or any other exception fails the test with the
mutations that caused it (Hypothesis shrinks them).

The default pass reads FUZZ_EXAMPLES inputs per file; the slow pass E3DPSM_FUZZ_EXAMPLES
(docs/testing.md has its counts and the command).
"""
from __future__ import annotations

import h5py
import numpy as np
import pytest
from hypothesis import given

from _bounded import BoundedWorker
from _camera_formats import camera_stream, encode_evt3
from _fuzz import (BOUND_S, FUZZ_EXAMPLES, SLOW_EXAMPLES, Counts, Seed, aedat4_fields, damaged, fuzz_settings,
                   outcome_label, write_input, zip_fields)
from e3dpsm.data.readers import write_events_h5

SEEDS = ("evt2.raw", "evt3.raw", "events.dat", "lz4.aedat4", "zstd.aedat4", "plain.aedat4", "ee3d.h5", "columns.hdf5",
         "plain.npz", "deflated.npz")


@pytest.fixture(scope="module")
def stream():
    """1,500 events over 40 s: EVT 3.0 wraps its time twice, AEDAT4 has several packets."""
    return camera_stream(n=1500, seed=2)


def _expelliarmus(stream, encoding: str, path) -> bytes:
    expelliarmus = pytest.importorskip("expelliarmus", reason="expelliarmus (pip extra cameras) is not installed")
    from expelliarmus.wizard.clib import event_t

    table = np.zeros(len(stream), dtype=event_t)
    table["t"], table["x"], table["y"], table["p"] = stream.t_us, stream.x, stream.y, stream.p
    expelliarmus.Wizard(encoding=encoding).save(path, table)
    return path.read_bytes()


def _aedat4(stream, compression: str, path) -> bytes:
    dv = pytest.importorskip("dv_processing", reason="dv-processing (pip extra cameras) is not installed")
    store = dv.EventStore()
    for t, x, y, p in zip(stream.t_us.tolist(), stream.x.tolist(), stream.y.tolist(), stream.p.tolist()):
        store.push_back(t, x, y, bool(p))
    writer = dv.io.MonoCameraWriter(str(path), dv.io.MonoCameraWriter.EventOnlyConfig(
        "DVXplorer_fuzz", (640, 480), getattr(dv.CompressionType, compression)))
    writer.setPackagingCount(400)  # several packets from a small file
    writer.writeEvents(store)
    del writer
    return path.read_bytes()


def _columns_hdf5(stream, path) -> bytes:
    with h5py.File(path, "w") as f:
        for key, values in (("x", stream.x), ("y", stream.y), ("t", stream.t_us), ("p", stream.p)):
            f[key] = values
        f.attrs["sensor_height"], f.attrs["sensor_width"] = 480, 640
    return path.read_bytes()


def make_seed(name: str, stream, folder) -> Seed:
    path = folder / name
    if name in ("evt2.raw", "events.dat"):
        return Seed(name, _expelliarmus(stream, "evt2" if name == "evt2.raw" else "dat", path), "expelliarmus")
    if name == "evt3.raw":
        return Seed(name, encode_evt3(stream, ["format EVT3;height=480;width=640", "end"]), "spec encoder (tests)")
    if name.endswith(".aedat4"):
        data = _aedat4(stream, {"lz4": "LZ4", "zstd": "ZSTD", "plain": "NONE"}[name.split(".")[0]], path)
        return Seed(name, data, "dv-processing", fields=aedat4_fields(data))
    if name == "ee3d.h5":
        write_events_h5(path, stream)
        return Seed(name, path.read_bytes(), "h5py (write_events_h5, LZF)", hot=((0, 4096),))
    if name == "columns.hdf5":
        return Seed(name, _columns_hdf5(stream, path), "h5py (separate datasets)", hot=((0, 4096),))
    save = np.savez if name == "plain.npz" else np.savez_compressed
    save(path, x=stream.x, y=stream.y, t=stream.t_us, p=stream.p)
    data = path.read_bytes()
    fields, hot = zip_fields(data)
    return Seed(name, data, f"numpy ({save.__name__})", fields=fields, hot=hot)


@pytest.fixture(scope="module")
def seeds(stream, tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz_seeds")
    return {name: make_seed(name, stream, folder) for name in SEEDS}


@pytest.fixture(scope="module")
def worker():
    with BoundedWorker(preload=("e3dpsm.data.readers", "_fuzz_targets", "h5py", "lz4.frame", "zstandard")) as bounded:
        yield bounded


def fuzz_pass(seed: Seed, worker: BoundedWorker, folder, examples: int, derandomize: bool = True) -> None:
    counts = Counts(f"read_events {seed.name} ({seed.writer})", BOUND_S)

    @fuzz_settings(examples, derandomize)
    @given(damaged(seed))
    def read_damaged(case):
        outcome = worker.call("_fuzz_targets:read_events", write_input(folder, seed, case.data), bound_s=BOUND_S)
        counts.add(outcome_label(outcome), outcome.seconds, "; ".join(case.steps))
        where = f"{seed.name} ({seed.writer}) after {list(case.steps)}"
        assert outcome.kind in ("returned", "refused"), f"{where}: {outcome.kind}: {outcome.detail}"
        if outcome.kind == "refused":
            assert outcome.detail.startswith("DataError: ") and "\n" not in outcome.detail, f"{where}: {outcome.detail}"

    try:
        read_damaged()
    finally:
        counts.report()


@pytest.mark.parametrize("name", SEEDS)
def test_every_seed_reads_back_its_events(seeds, worker, stream, tmp_path, name):
    """The undamaged files are what the fuzzing starts from: each reads back every event."""
    outcome = worker.call("_fuzz_targets:read_events", write_input(tmp_path, seeds[name], seeds[name].data),
                          bound_s=BOUND_S)
    assert outcome.kind == "returned" and outcome.value == len(stream), outcome


@pytest.mark.parametrize("name", SEEDS)
def test_damaged_files_end_with_events_or_one_error_line(seeds, worker, tmp_path, name):
    fuzz_pass(seeds[name], worker, tmp_path, FUZZ_EXAMPLES)


@pytest.mark.slow
@pytest.mark.parametrize("name", SEEDS)
def test_damaged_files_long_pass(seeds, worker, tmp_path, name):
    fuzz_pass(seeds[name], worker, tmp_path, SLOW_EXAMPLES, derandomize=False)
