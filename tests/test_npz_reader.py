"""e3dpsm/data/formats/npz.py at its edges: deflate's 1032:1 bound (zlib's own figure for its
best case, zlib.net/zlib_tech.html) taken exactly, the two .npy format versions numpy writes
for such arrays, the dtypes that are numbers, and each refusal's one line. (Damaged files at
random: the fuzz tests; pickles and headers that lie: tests/test_readers.py.)"""
from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
from numpy.lib import format as npy

from e3dpsm.data.formats import npz
from e3dpsm.errors import DataError

EVENTS = {"x": np.arange(5, dtype=np.int32), "y": np.arange(5, dtype=np.int32),
          "t": np.arange(5, dtype=np.int64), "p": np.ones(5, np.uint8)}


def _write(path, arrays: dict, version: tuple[int, int] | None = None, compress: bool = False) -> None:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED) as archive:
        for key, array in arrays.items():
            buffer = io.BytesIO()
            npy.write_array(buffer, np.asarray(array), version=version, allow_pickle=False)
            archive.writestr(f"{key}.npy", buffer.getvalue())


def _refused(path, **kwargs) -> str:
    with pytest.raises(DataError) as info:
        npz.load_arrays(path, **kwargs) if kwargs else npz.read_npz(path)
    return str(info.value).removeprefix(f"{path}: ")


def test_deflates_bound_is_taken_exactly(tmp_path) -> None:
    """A member may claim at most 1032 times its compressed size plus 1 KiB of slack: at the
    bound the claim passes the ratio check (and is then refused by the size the .npy header
    declares); one byte more is refused as more than deflate can expand."""
    path = tmp_path / "ev.npz"
    _write(path, EVENTS, compress=True)
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("x.npy")
        real = info.file_size
        info.file_size = npz.DEFLATE_MAX_RATIO * info.compress_size + 1024
        with pytest.raises(DataError) as at_bound:
            npz._check_member(archive, info, "x", 1, path)
        info.file_size += 1
        with pytest.raises(DataError) as over:
            npz._check_member(archive, info, "x", 1, path)
        info.file_size = real
        npz._check_member(archive, info, "x", 1, path)
    assert npz.DEFLATE_MAX_RATIO == 1032
    assert "declares 5 values of int32 but its member holds" in str(at_bound.value)
    assert str(over.value) == (f"{path}: array x claims {npz.DEFLATE_MAX_RATIO * info.compress_size + 1025} bytes "
                               f"from {info.compress_size} compressed; more than deflate can expand (corrupted?)")


def test_stored_members_have_no_ratio_to_check(tmp_path) -> None:
    path = tmp_path / "ev.npz"
    _write(path, EVENTS)
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("t.npy")
        assert info.compress_type == zipfile.ZIP_STORED
        npz._check_member(archive, info, "t", 1, path)


def test_both_npy_versions_numpy_writes_are_read_and_a_third_is_refused(tmp_path) -> None:
    for version in ((1, 0), (2, 0)):
        _write(tmp_path / f"v{version[0]}.npz", EVENTS, version=version)
        got = npz.read_npz(tmp_path / f"v{version[0]}.npz")
        assert all(np.array_equal(got[k], EVENTS[k]) for k in EVENTS)
    _write(tmp_path / "v3.npz", EVENTS, version=(3, 0))
    assert _refused(tmp_path / "v3.npz") == "array x has .npy format version (3, 0); expected 1.0 or 2.0"


@pytest.mark.parametrize("dtype", [np.complex64, "U3", "S2", "datetime64[s]"])
def test_arrays_that_are_not_plain_numbers_are_refused(tmp_path, dtype) -> None:
    path = tmp_path / "ev.npz"
    _write(path, {**EVENTS, "x": np.zeros(5, dtype)})
    assert _refused(path) == (f"array x has dtype {np.dtype(dtype)}; expected numbers (object arrays would be "
                              "pickles)")


def test_booleans_and_every_integer_and_float_width_are_numbers(tmp_path) -> None:
    path = tmp_path / "ev.npz"
    arrays = {"b": np.ones(3, bool), "i": np.ones(3, np.int8), "u": np.ones(3, np.uint16), "f": np.ones(3, np.float16)}
    _write(path, arrays)
    got = npz.load_arrays(path)
    assert sorted(got) == ["b", "f", "i", "u"] and all(got[k].dtype == arrays[k].dtype for k in arrays)


def test_a_missing_array_and_a_wrong_dimension_count_are_named(tmp_path) -> None:
    path = tmp_path / "ev.npz"
    _write(path, {k: v for k, v in EVENTS.items() if k != "p"})
    assert _refused(path) == "missing arrays ['p']; expected x, y, t, p"
    _write(path, {"frames": np.zeros(4)})
    assert _refused(path, keys=("frames",), ndim=2) == "array frames has shape (4,); expected 2 dimensions"
    assert _refused(path, keys=("frames", "poses")) == "missing arrays ['poses']; expected frames, poses"
    assert npz.load_arrays(path, keys=("frames",), ndim=1)["frames"].shape == (4,)
