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



def test_golden_with_the_recorded_tolerance_profiles_loads(tmp_path):
    """AttributeError 'budget_pct' out of every `golden check` (the long fuzz pass, flip 0 of
    any input): the store's checks read two fields the budget profiles no longer have."""
    from e3dpsm.golden.store import load_golden
    from e3dpsm.golden.tolerances import PROFILES

    folder = small_golden(tmp_path / "g")
    _edit_manifest(folder, lambda m: m.update(tolerances={name: p.to_dict() for name, p in PROFILES.items()}))
    assert load_golden(folder).manifest["tolerances"]["int8"] == {"name": "int8", "kind": "budget", "state_rtol": 0.5,
                                                                  "max_growth": 4.0, "growth_floor": 0.05}
    _edit_manifest(folder, lambda m: m["tolerances"]["int8"].update(max_growth=-4.0))
    with pytest.raises(DataError, match=r"golden\.json: tolerance profile 'int8' is broken \(.*\); record the golden "
                                        r"again$"):
        load_golden(folder)
    _edit_manifest(folder, lambda m: m["tolerances"]["int8"].update(max_growth=4.0, growth_floor=-0.05))
    with pytest.raises(DataError, match=r"tolerance profile 'int8' is broken"):
        load_golden(folder)
    _edit_manifest(folder, lambda m: m["tolerances"]["fp32"].pop("pose_atol_mm"))
    _edit_manifest(folder, lambda m: m["tolerances"]["int8"].update(growth_floor=0.05))
    with pytest.raises(DataError, match=r"tolerance profile 'fp32' is broken"):
        load_golden(folder)

# `run` and a corrupted timestamp ----------------------------------------------------------------
def _gap_npz(path, gap_s: float) -> None:
    """Four events, the last `gap_s` after the third: what one corrupted timestamp makes."""
    t = np.array([1_000, 2_000, 3_000, 3_000 + int(gap_s * 1e6)], dtype=np.int64)
    np.savez(path, x=np.array([1, 2, 3, 4]), y=np.array([1, 2, 3, 4]), t=t, p=np.array([0, 1, 0, 1]))


@pytest.fixture(scope="module")
def tiny_graph(tmp_path_factory):
    from _runtime_helpers import exported_tiny

    return exported_tiny(str(tmp_path_factory.getbasetemp()))[1]


def test_run_refuses_an_hour_of_silence_in_seconds_instead_of_stepping_it(tiny_graph, tmp_path):
    """A 4-event file whose last timestamp sits an hour late kept `run` stepping 180,000 empty
    windows (over 120 s with the tiny graph; a timestamp with a flipped high bit: forever)."""
    from _bounded import BoundedWorker

    _gap_npz(tmp_path / "gap.npz", 3600)
    (tmp_path / "out").mkdir()
    argv = ["run", "--model", str(tiny_graph), "--events", str(tmp_path / "gap.npz"), "--out",
            str(tmp_path / "out" / "poses.csv"), "--threads", "1", "--no-progress"]
    with BoundedWorker(preload=("_fuzz_targets", "e3dpsm.cli.run")) as worker:
        outcome = worker.call("_fuzz_targets:run_cli", argv, bound_s=60)
        assert outcome.kind == "returned", outcome
        code, _, err = outcome.value
        assert code == 2 and err.splitlines() == [
            f"e3dpsm run: error: {tmp_path / 'gap.npz'}: events 2 and 3 are 3600 s apart: 180,000 empty 20 ms windows "
            "to step. No event camera is silent that long: a timestamp is corrupted, or pass --max-gap-s 3600 to run "
            "it as it is"]
        assert list((tmp_path / "out").iterdir()) == []
        np.savez(tmp_path / "fine.npz", x=[1, 2], y=[1, 2], t=[1_000, 500_000], p=[0, 1])  # many files: each checked
        code, _, err = worker.call("_fuzz_targets:run_cli", ["run", "--model", str(tiny_graph), "--events",
                                   str(tmp_path / "fine.npz"), str(tmp_path / "gap.npz"), "--out",
                                   str(tmp_path / "out"), "--no-progress"], bound_s=60).value
        assert code == 2 and "gap.npz: events 2 and 3 are 3600 s apart" in err and len(err.splitlines()) == 1
        assert list((tmp_path / "out").iterdir()) == []
        _gap_npz(tmp_path / "gap.npz", 61)  # just over the default: allowed with --max-gap-s
        assert worker.call("_fuzz_targets:run_cli", argv, bound_s=60).value[0] == 2
        outcome = worker.call("_fuzz_targets:run_cli", [*argv, "--max-gap-s", "62", "--window-ms", "200"], bound_s=120)
    assert outcome.kind == "returned" and outcome.value[0] == 0, outcome
    assert len((tmp_path / "out" / "poses.csv").read_text().splitlines()) == 1 + 305  # header + every window


def test_the_gap_check_spans_chunks_as_the_live_source_delivers_them():
    from e3dpsm.runtime.run_output import check_gaps

    check_gaps(np.array([5_000_000, 6_000_000]), 60, 20, "dv://h:1", previous_us=0)  # 5 s: fine
    with pytest.raises(DataError, match=r"^dv://h:1: event 0 and the event before it are 70 s apart: 3,500 empty "
                                        r"20 ms windows"):
        check_gaps(np.array([70_000_000]), 60, 20, "dv://h:1", previous_us=0)
    check_gaps(np.array([], dtype=np.int64), 60, 20, "x", previous_us=0)


def test_npz_whose_npy_header_has_unbalanced_brackets_is_one_error_line(tmp_path):
    """tokenize.TokenError ("EOF in multi-line statement") escaped numpy's .npy header parser
    and the reader (found by atheris, tests/fuzz/atheris_readers.py npz, in 565 runs)."""
    header = b"{'descr': '<i8', 'fortran_order': False, 'shape': (2, }"
    header += b" " * (63 - (10 + len(header)) % 64) + b"\n"  # the format's 64-byte alignment
    npy = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(16)
    with zipfile.ZipFile(tmp_path / "ev.npz", "w") as archive:
        for key in "xytp":
            archive.writestr(f"{key}.npy", npy)
    with pytest.raises(DataError, match=r"ev\.npz: cannot read \.npz file \(truncated or corrupted\?\): .*EOF in "
                                        r"multi-line statement"):
        read_events(tmp_path / "ev.npz")
