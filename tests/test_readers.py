"""Event file readers/writers, the restricted unpickler, and the EE3D layout reader."""
from __future__ import annotations

import json
import pickle

import h5py
import numpy as np
import pytest

from e3dpsm.data.ee3d import read_ee3d_sequence
from e3dpsm.data.readers import read_events, read_events_with_frames, write_events_h5
from e3dpsm.data.safe_pickle import safe_load_pickle, safe_loads
from e3dpsm.data.sequence import EventStream
from e3dpsm.errors import DataError


def random_stream(n: int = 500, seed: int = 0) -> EventStream:
    rng = np.random.default_rng(seed)
    return EventStream(
        x=rng.integers(0, 640, n).astype(np.int32), y=rng.integers(0, 480, n).astype(np.int32),
        t_us=np.sort(rng.integers(0, 1_000_000, n)).astype(np.int64), p=rng.integers(0, 2, n).astype(np.uint8),
    )


def assert_same_stream(a: EventStream, b: EventStream) -> None:
    for name in ("x", "y", "t_us", "p"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.sensor_hw == b.sensor_hw


def test_h5_round_trip_with_frame_index(tmp_path):
    stream = random_stream()
    frames = np.arange(len(stream)) // 50
    write_events_h5(tmp_path / "events.h5", stream, frames)
    back, back_frames = read_events_with_frames(tmp_path / "events.h5")
    assert_same_stream(back, stream)
    np.testing.assert_array_equal(back_frames, frames)
    assert back.x.dtype == np.int32 and back.t_us.dtype == np.int64 and back.p.dtype == np.uint8
    assert [p.name for p in tmp_path.iterdir()] == ["events.h5"]  # no temporary left behind


def test_h5_with_separate_datasets_and_meta_json(tmp_path):
    stream = random_stream()
    with h5py.File(tmp_path / "ev.hdf5", "w") as f:
        for key, values in (("x", stream.x), ("y", stream.y), ("t", stream.t_us), ("p", stream.p)):
            f[key] = values
    (tmp_path / "event_meta.json").write_text(json.dumps({"height": 500, "width": 700}))
    back = read_events(tmp_path / "ev.hdf5")
    assert back.sensor_hw == (500, 700)
    np.testing.assert_array_equal(back.t_us, stream.t_us)


def test_npz_round_trip_repairs_signed_polarity(tmp_path):
    stream = random_stream()
    np.savez(tmp_path / "ev.npz", x=stream.x, y=stream.y, t=stream.t_us, p=stream.p.astype(np.int8) * 2 - 1)
    assert_same_stream(read_events(tmp_path / "ev.npz", sensor_hw=(480, 640)), stream)


def test_truncated_h5_is_a_data_error_naming_the_file(tmp_path):
    path = tmp_path / "events.h5"
    write_events_h5(path, random_stream(5000))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="events.h5"):
        read_events(path)


@pytest.mark.parametrize("name", ["missing.h5", "broken.npz", "events.txt", "short.npz", "bad_values.h5"])
def test_unreadable_files_are_data_errors(tmp_path, name):
    path = tmp_path / name
    if name == "broken.npz":
        path.write_bytes(b"PK\x03\x04 not really a zip")
    elif name == "events.txt":
        path.write_text("1 2 3 4\n")
    elif name == "short.npz":
        np.savez(path, x=np.zeros(2), y=np.zeros(2), t=np.zeros(2))
    elif name == "bad_values.h5":
        with h5py.File(path, "w") as f:
            f["event"] = np.array([[1, 1, 10, 0], [1, 1, 5, 0]])  # time goes backwards
    with pytest.raises(DataError, match=name.replace(".", r"\.")):
        read_events(path)


# restricted unpickler ---------------------------------------------------------------------------

class _Exploit:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        import os

        return os.system, (f"touch {self.marker}",)


def test_malicious_pickle_is_refused_without_running(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "gt.pickle"
    path.write_bytes(pickle.dumps([{"ego_j3d": np.zeros((16, 3))}, _Exploit(marker)]))
    with pytest.raises(DataError, match=r"refusing to unpickle (posix|os|nt)\.system"):
        safe_load_pickle(path)
    assert not marker.exists()


def test_arbitrary_class_is_refused():
    with pytest.raises(DataError, match="refusing to unpickle tests.test_readers.random_stream|refusing"):
        safe_loads(pickle.dumps(EventStream(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))))


@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_plain_data_and_numpy_arrays_load(protocol):
    value = {
        "ego_j3d": np.arange(48, dtype=np.float64).reshape(16, 3), "n": np.int64(7), "f": np.float32(0.5),
        "items": [1, 2.5, "s", b"b", None, True, (1, 2), {3}], "dt": np.dtype("<f4"),
    }
    back = safe_loads(pickle.dumps(value, protocol=protocol))
    np.testing.assert_array_equal(back["ego_j3d"], value["ego_j3d"])
    assert back["n"] == 7 and back["f"] == np.float32(0.5) and back["dt"] == np.dtype("<f4")
    assert back["items"] == value["items"]


def test_truncated_pickle_is_a_data_error():
    with pytest.raises(DataError, match="corrupted pickle"):
        safe_loads(pickle.dumps(list(range(100)))[:-20])


# EE3D layout ----------------------------------------------------------------------------------

def write_ee3d_folder(folder, rng):
    """A 4-frame EE3D sequence; frame 2 has no events and cannot be timed."""
    folder.mkdir()
    frames = np.array([0] * 30 + [1] * 30 + [3] * 40 + [-1] * 5)
    n = len(frames)
    stream = EventStream(
        x=rng.integers(0, 640, n).astype(np.int32), y=rng.integers(0, 480, n).astype(np.int32),
        t_us=np.arange(n, dtype=np.int64) * 500 + 10_000, p=rng.integers(0, 2, n).astype(np.uint8),
    )
    write_events_h5(folder / "events.h5", stream, frames)
    (folder / "event_meta.json").write_text(json.dumps({"height": 480, "width": 640}))
    j3d = rng.normal(size=(4, 16, 3))
    j2d = rng.uniform(0, 400, size=(4, 16, 2))
    gt = [{"ego_j3d": j3d[f], "ego_j2d": j2d[f], "extra": "ignored"} for f in range(4)]
    (folder / "synced_local_pose_gt.pickle").write_bytes(pickle.dumps(gt))
    (folder / "valid_joints").mkdir()
    flags = [1] * 16
    flags[5] = 0
    (folder / "valid_joints" / "000003.json").write_text(json.dumps(flags))
    (folder / "valid_joints" / "0.json").write_text(json.dumps([True] * 15 + [False]))
    return stream, j3d, j2d


def test_ee3d_folder_reads_into_a_sequence_with_the_rotation_applied(tmp_path):
    stream, j3d, j2d = write_ee3d_folder(tmp_path / "seq_a", np.random.default_rng(3))
    seq = read_ee3d_sequence(tmp_path / "seq_a")
    assert seq.name == "seq_a" and seq.meta["layout"] == "ee3d"
    kept = [0, 1, 3]  # frame 2 had no events
    assert seq.meta["dropped_frames_without_events"] == 1
    # 180 degrees about x: (x, y, z) -> (x, -y, -z)
    np.testing.assert_allclose(seq.j3d_m, j3d[kept] * np.array([1, -1, -1]), rtol=1e-6)
    np.testing.assert_allclose(seq.j2d_px, j2d[kept], rtol=1e-6)
    # pose time: last event of the frame + 1 us
    np.testing.assert_array_equal(seq.t_us, stream.t_us[[29, 59, 99]] + 1)
    assert seq.visible.shape == (3, 16)
    assert seq.visible[0, 15] == 0 and seq.visible[0, :15].all()
    assert seq.visible[1].all()  # no file: visible
    assert seq.visible[2, 5] == 0 and seq.visible[2].sum() == 15
    assert (seq.action == -1).all()
    assert len(seq.events) == len(stream)


def test_ee3d_missing_pose_keys_is_a_data_error(tmp_path):
    write_ee3d_folder(tmp_path / "seq_b", np.random.default_rng(4))
    (tmp_path / "seq_b" / "synced_local_pose_gt.pickle").write_bytes(pickle.dumps([{"j3d": 1}] * 4))
    with pytest.raises(DataError, match="frame 0 needs 'ego_j3d'"):
        read_ee3d_sequence(tmp_path / "seq_b")


# .npz: no pickles, work bounded by the file --------------------------------------------------------

def test_npz_with_a_pickled_object_array_is_refused_without_running_it(tmp_path):
    marker = tmp_path / "pwned"
    stream = random_stream(10)
    np.savez(tmp_path / "ev.npz", x=stream.x, y=stream.y, t=stream.t_us,
             p=np.array([_Exploit(marker)] * 10, dtype=object))
    with pytest.raises(DataError, match=r"ev\.npz: array p has dtype object; expected numbers \(object arrays would "
                                        r"be pickles\)$"):
        read_events(tmp_path / "ev.npz")
    assert not marker.exists()


def test_npz_with_a_two_dimensional_array_is_refused(tmp_path):
    stream = random_stream(10)
    np.savez(tmp_path / "ev.npz", x=stream.x.reshape(2, 5), y=stream.y, t=stream.t_us, p=stream.p)
    with pytest.raises(DataError, match=r"array x has shape \(2, 5\); expected one dimension$"):
        read_events(tmp_path / "ev.npz")


def test_npz_whose_header_claims_more_values_than_its_member_holds_is_refused_before_reading(tmp_path):
    """A damaged shape is named, not allocated (10^15 int64 values would be 8 PB). The archive is
    written by zipfile with a correct CRC: the damage is in the .npy header alone."""
    import io
    import zipfile

    stream = random_stream(100)
    with zipfile.ZipFile(tmp_path / "ev.npz", "w") as archive:
        for key, values in (("x", stream.x), ("y", stream.y), ("t", stream.t_us), ("p", stream.p)):
            npy = io.BytesIO()
            np.save(npy, values)
            data = npy.getvalue()
            if key == "t":
                old = b"'shape': (100,), }" + b" " * 13
                assert data.count(old) == 1
                data = data.replace(old, b"'shape': (1000000000000000,), }")  # the same header length
            archive.writestr(f"{key}.npy", data)
    with pytest.raises(DataError, match=r"array t declares 1000000000000000 values of int64 but its member holds "
                                        r"800 bytes of data"):
        read_events(tmp_path / "ev.npz")


def test_npz_member_claiming_more_than_deflate_can_expand_is_refused(tmp_path):
    stream = random_stream(100)
    np.savez_compressed(tmp_path / "ev.npz", x=stream.x, y=stream.y, t=stream.t_us, p=stream.p)
    data = bytearray((tmp_path / "ev.npz").read_bytes())
    import zipfile

    with zipfile.ZipFile(tmp_path / "ev.npz") as archive:
        names = [info.filename for info in archive.infolist()]
    entry = data.index(b"PK\x01\x02")  # the central directory's first entry: x.npy
    assert names[0] == "x.npy"
    data[entry + 24:entry + 28] = (2**31).to_bytes(4, "little")  # its uncompressed size
    (tmp_path / "ev.npz").write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"array x claims 2147483648 bytes from \d+ compressed; more than deflate can "
                                        r"expand"):
        read_events(tmp_path / "ev.npz")
