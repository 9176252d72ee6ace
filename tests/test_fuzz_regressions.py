"""One test per bug the fuzz tests (tests/test_fuzz_*.py) found, on the smallest input that
showed it. Each failed before its fix: a traceback where one DataError line belongs."""
from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from _camera_formats import camera_stream, encode_evt3
from _fuzz_seeds import small_golden
from e3dpsm.data.readers import read_events
from e3dpsm.errors import DataError


def test_npz_whose_deflate_data_is_damaged_is_one_error_line(tmp_path):
    """zlib.error ("invalid stored block lengths") escaped the .npz reader."""
    path = tmp_path / "ev.npz"
    stream = camera_stream(n=200, seed=1)
    np.savez_compressed(path, x=stream.x, y=stream.y, t=stream.t_us, p=stream.p)
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        local = archive.getinfo("x.npy").header_offset
    start = local + 30 + int.from_bytes(data[local + 26:local + 28], "little") + int.from_bytes(
        data[local + 28:local + 30], "little")  # after the local header's name and extra field
    data[start] = 0b111  # the first deflate block header: final, type 3 (reserved, invalid)
    path.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"ev\.npz: cannot read \.npz file \(truncated or corrupted\?\): Error -3 "
                                        r"while decompressing data: invalid block type$"):
        read_events(path)


@pytest.mark.parametrize("header", [["format EVT3;height=480;width=\x00640"], ["format EVT3;height=-480;width=640"],
                                    ["evt 3.0", "geometry 640x0"]])
def test_raw_header_whose_sensor_size_is_not_a_positive_number_is_one_error_line(tmp_path, header):
    """int() of "\\x00640" raised ValueError out of the RAW reader (the geometry line already
    had its message; the format line and DAT's Width/Height had none)."""
    path = tmp_path / "rec.raw"
    path.write_bytes(encode_evt3(camera_stream(n=50, seed=1), [*header, "end"]))
    with pytest.raises(DataError, match=r"rec\.raw: header line '% (format|geometry) .*' does not state a sensor "
                                        r"size in positive whole numbers$"):
        read_events(path)


# the golden store ------------------------------------------------------------------------------
def test_a_small_golden_loads(tmp_path):
    from e3dpsm.golden.store import load_golden

    record = load_golden(small_golden(tmp_path / "g"))
    assert record.steps == 3 and record.frame(2).shape == (1, 2, 4, 4) and record.state_index("s").shape == (32,)


def _edit_manifest(folder, edit) -> None:
    manifest = json.loads((folder / "golden.json").read_text())
    edit(manifest)
    (folder / "golden.json").write_text(json.dumps(manifest))


def test_golden_whose_state_has_no_name_is_one_error_line(tmp_path):
    """KeyError 'name' escaped `golden check` (the fuzz tests deleted states/4/name)."""
    from e3dpsm.golden.store import load_golden

    folder = small_golden(tmp_path / "g")
    _edit_manifest(folder, lambda m: m["states"][0].pop("name"))
    with pytest.raises(DataError, match=r"golden\.json: 'states' is .*, expected a list of \{name, shape: \[batch, "
                                        r"dims\.\.\.\]\} with distinct names; record the golden again$"):
        load_golden(folder)


def test_golden_whose_arrays_fail_their_crc_is_one_error_line(tmp_path):
    """zipfile.BadZipFile ("Bad CRC-32 for file 'lnes.mask.npy'") escaped `golden check`."""
    from e3dpsm.golden.store import load_golden

    folder = small_golden(tmp_path / "g")
    data = bytearray((folder / "rollout.npz").read_bytes())
    with zipfile.ZipFile(folder / "rollout.npz") as archive:
        info = archive.getinfo("window_ms.npy")
    local = info.header_offset
    start = local + 30 + int.from_bytes(data[local + 26:local + 28], "little") + int.from_bytes(
        data[local + 28:local + 30], "little")
    data[start + info.compress_size - 5] ^= 0x01  # near the end of its deflate data: a CRC or zlib error
    (folder / "rollout.npz").write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"rollout\.npz: cannot read the arrays \(truncated or corrupted\?\): .*"):
        load_golden(folder)
