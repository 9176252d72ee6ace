"""The undamaged files the fuzz tests start from, each made by an independent writer:
expelliarmus (EVT 2.0, DAT), dv-processing (AEDAT4 with LZ4, Zstd, no compression), h5py (the
EE3D layout through write_events_h5, separate datasets), numpy (savez, savez_compressed), and
the tests' spec encoder for EVT 3.0 (expelliarmus' EVT 3.0 writer is wrong, docs/cameras.md);
and a small golden record by the project's own writer."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from _camera_formats import camera_stream, encode_evt3
from _fuzz import Seed, aedat4_fields, zip_fields
from e3dpsm.data.readers import write_events_h5

SEEDS = ("evt2.raw", "evt3.raw", "events.dat", "lz4.aedat4", "zstd.aedat4", "plain.aedat4", "ee3d.h5", "columns.hdf5",
         "plain.npz", "deflated.npz")


def seed_stream():
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
    if name == "ee3d.h5":  # hot: the metadata, and the LZF chunks (one byte there crashed h5py)
        write_events_h5(path, stream)
        with h5py.File(path, "r") as f:
            chunks = [f["event"].id.get_chunk_info(i) for i in range(f["event"].id.get_num_chunks())]
        hot = ((0, 4096), *((c.byte_offset, c.byte_offset + c.size) for c in chunks))
        return Seed(name, path.read_bytes(), "h5py (write_events_h5, LZF)", hot=hot)
    if name == "columns.hdf5":
        return Seed(name, _columns_hdf5(stream, path), "h5py (separate datasets)", hot=((0, 4096),))
    save = np.savez if name == "plain.npz" else np.savez_compressed
    save(path, x=stream.x, y=stream.y, t=stream.t_us, p=stream.p)
    data = path.read_bytes()
    fields, hot = zip_fields(data)
    return Seed(name, data, f"numpy ({save.__name__})", fields=fields, hot=hot)


JOINTS = [f"j{i}" for i in range(16)]


def small_golden(folder, steps: int = 3):
    """A golden record written by the project's writer (GoldenWriter): 2 x 4 x 4 frames, one
    output, one state of 100 elements (sampled: 32 of them)."""
    from e3dpsm.golden.store import GoldenWriter

    rng = np.random.default_rng(0)
    writer = GoldenWriter((2, 4, 4), ["pose"], {"s": (100,)}, steps)
    for _ in range(steps):
        frame = (rng.random((2, 4, 4)) * (rng.random((2, 4, 4)) < 0.3)).astype(np.float16)
        writer.add(frame, 20.0, rng.normal(size=(16, 3)), {"pose": rng.normal(size=(1, 16, 3))},
                   {"s": rng.normal(size=(1, 100))})
    writer.write(folder, {"source": {"kind": "onnx", "variant": "tiny"}, "joints": JOINTS, "window_ms": 20.0,
                          "states": [{"name": "s", "shape": ["batch", 100]}], "mpjpe_scale_mm": 80.0})
    return folder
