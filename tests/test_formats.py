"""Camera recordings (AEDAT4, Prophesee RAW EVT 2.0 / 3.0, DAT): decoded events equal the
HDF5 they came from exactly; `run` gives byte-identical pose CSVs; damaged files name the byte."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _camera_formats import _header as header_bytes, camera_stream, encode_dat, encode_evt2, encode_evt3
from _runtime_helpers import exported_tiny, synthetic_stream
from e3dpsm.cli import main
from e3dpsm.data.readers import read_events, write_events_h5
from e3dpsm.data.sequence import EventStream
from e3dpsm.errors import DataError

RAW2_HEADER = ["evt 2.0", "geometry 640x480"]  # older Metavision header
RAW3_HEADER = ["camera_integrator_name Prophesee", "format EVT3;height=480;width=640", "end"]  # newer one
DAT_HEADER = ["Data file containing CD events", "Version 2", "Width 640", "Height 480"]
ENCODERS = {
    "evt2.raw": lambda s: encode_evt2(s, RAW2_HEADER),
    "evt3.raw": lambda s: encode_evt3(s, RAW3_HEADER),
    "events.dat": lambda s: encode_dat(s, DAT_HEADER),
}


def assert_same_events(got: EventStream, want: EventStream) -> None:
    assert len(got) == len(want)
    for name in ("x", "y", "t_us", "p"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    assert got.sensor_hw == want.sensor_hw


def write_aedat4(path, stream: EventStream, camera: str = "DVXplorer_test", compression: str = "LZ4",
                 triggers_first: bool = False) -> None:
    """AEDAT4 by iniVation's own writer (dv-processing MonoCameraWriter). `triggers_first`:
    a trigger stream (id 0, two triggers) before the event stream (id 1)."""
    dv = pytest.importorskip("dv_processing", reason="dv-processing (pip extra cameras) is not installed")
    store = dv.EventStore()
    for t, x, y, p in zip(stream.t_us.tolist(), stream.x.tolist(), stream.y.tolist(), stream.p.tolist()):
        store.push_back(t, x, y, bool(p))
    height, width = stream.sensor_hw
    config = dv.io.MonoCameraWriter.Config(camera, getattr(dv.CompressionType, compression))
    if triggers_first:  # the writer numbers streams by name: "a_triggers" before "events"
        config.addTriggerStream("a_triggers")
    config.addEventStream((width, height))
    writer = dv.io.MonoCameraWriter(str(path), config)
    if triggers_first:
        for t in (int(stream.t_us[0]), int(stream.t_us[-1])):
            writer.writeTrigger(dv.Trigger(t, dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE), "a_triggers")
    writer.writeEvents(store)
    del writer  # closes the file (writes its data table)


def read_with_dv_processing(path) -> np.ndarray:
    """The events dv-processing's own reader gives (safe on undamaged files only)."""
    import dv_processing as dv

    recording = dv.io.MonoCameraRecording(str(path))
    batches = []
    while (batch := recording.getNextEventBatch()) is not None:
        batches.append(batch.numpy())
    return np.concatenate(batches)


@pytest.fixture(scope="module")
def camera_events(tmp_path_factory):
    """One stream in every format, next to the HDF5 it came from."""
    folder = tmp_path_factory.mktemp("camera")
    stream = camera_stream()
    write_events_h5(folder / "events.h5", stream)
    for name, encode in ENCODERS.items():
        (folder / name).write_bytes(encode(stream))
    return folder, stream


def test_the_fixtures_exercise_every_decoder_path(camera_events):
    folder, stream = camera_events
    words = np.frombuffer((folder / "evt3.raw").read_bytes().split(b"% end\n")[1], "<u2") >> 12
    counts = {kind: int(np.sum(words == code)) for kind, code in (("vect12", 4), ("vect8", 5), ("single", 2))}
    assert min(counts.values()) > 10, counts
    assert stream.t_us[-1] - stream.t_us[0] > 2 * 2**24  # EVT 3.0's 24-bit time wraps twice


@pytest.mark.parametrize("name", list(ENCODERS))
def test_spec_encoded_prophesee_files_read_back_the_hdf5_events(camera_events, name):
    folder, stream = camera_events
    want = read_events(folder / "events.h5")
    assert_same_events(read_events(folder / name), want)
    assert read_events(folder / name).sensor_hw == (480, 640)  # from the header, not a default


@pytest.mark.parametrize("encoding, suffix", [("evt2", "raw"), ("dat", "dat")])
def test_files_by_expelliarmus_writer_read_back_the_hdf5_events(tmp_path, encoding, suffix):
    """expelliarmus's own writer (its EVT 3.0 writer omits time-high words, see docs/cameras.md)."""
    expelliarmus = pytest.importorskip("expelliarmus", reason="expelliarmus is not installed")
    from expelliarmus.wizard.clib import event_t

    stream = camera_stream(seed=3)
    table = np.zeros(len(stream), dtype=event_t)
    table["t"], table["x"], table["y"], table["p"] = stream.t_us, stream.x, stream.y, stream.p
    expelliarmus.Wizard(encoding=encoding).save(tmp_path / f"e.{suffix}", table)
    write_events_h5(tmp_path / "events.h5", stream)
    # expelliarmus writes no sensor size: the reader's fallback (the EE3D 480 x 640) applies
    assert_same_events(read_events(tmp_path / f"e.{suffix}"), read_events(tmp_path / "events.h5"))


def test_aedat4_by_dv_processing_reads_back_the_hdf5_events_with_epoch_timestamps(tmp_path):
    base = camera_stream(seed=5)
    stream = EventStream(base.x, base.y, base.t_us + 1_700_000_000_000_000, base.p, sensor_hw=(480, 640))
    write_aedat4(tmp_path / "rec.aedat4", stream)
    write_events_h5(tmp_path / "events.h5", stream)
    got = read_events(tmp_path / "rec.aedat4")
    assert_same_events(got, read_events(tmp_path / "events.h5"))
    assert got.t_us.dtype == np.int64 and got.t_us[0] > 10**15


def test_sensor_size_comes_from_the_aedat4_stream_info(tmp_path):
    rng = np.random.default_rng(1)
    n = 200
    stream = EventStream(rng.integers(0, 346, n).astype(np.int32), rng.integers(0, 260, n).astype(np.int32),
                         np.sort(rng.integers(0, 10**6, n)).astype(np.int64), rng.integers(0, 2, n).astype(np.uint8),
                         sensor_hw=(260, 346))
    write_aedat4(tmp_path / "davis.aedat4", stream, camera="DAVIS346_test")
    assert read_events(tmp_path / "davis.aedat4").sensor_hw == (260, 346)


def test_raw_header_forms_and_unsupported_encodings(tmp_path):
    stream = camera_stream(n=50, seed=2)
    (tmp_path / "a.raw").write_bytes(encode_evt2(stream, ["format EVT2;width=1280;height=720"]))
    assert read_events(tmp_path / "a.raw").sensor_hw == (720, 1280)
    (tmp_path / "b.raw").write_bytes(encode_evt2(stream, ["format EVT21;width=1280;height=720"]))
    with pytest.raises(DataError, match=r"b\.raw: unsupported RAW encoding \('EVT21;.*EVT 2\.0, EVT 3\.0"):
        read_events(tmp_path / "b.raw")
    (tmp_path / "c.raw").write_bytes(encode_evt2(stream, ["date today"]))
    with pytest.raises(DataError, match="no '% format' or '% evt' line"):
        read_events(tmp_path / "c.raw")


@pytest.mark.parametrize("name, cut, record_start", [
    ("evt2.raw", 4 * 200 + 2, 4 * 200), ("evt3.raw", 2 * 301 + 1, 2 * 301), ("events.dat", 2 + 8 * 100 + 5, 2 + 8 * 100),
])
def test_truncated_prophesee_file_names_the_byte_of_the_cut_record(camera_events, tmp_path, name, cut, record_start):
    folder, _ = camera_events
    data = (folder / name).read_bytes()
    header_end = len(header_bytes({"evt2.raw": RAW2_HEADER, "evt3.raw": RAW3_HEADER, "events.dat": DAT_HEADER}[name]))
    (tmp_path / name).write_bytes(data[:header_end + cut])
    with pytest.raises(DataError, match=rf"{name}: truncated: .* at byte {header_end + record_start} .*ends at byte "
                                        rf"{header_end + cut}$"):
        read_events(tmp_path / name)


def test_evt3_events_before_the_first_time_high_or_row_are_dropped(tmp_path):
    """The specification starts decoding at the first time-high; an event needs a row too."""
    words = [(0x0 << 12) | 7, (0x2 << 12) | 1, (0x8 << 12) | 3, (0x6 << 12) | 5, (0x2 << 12) | (1 << 11) | 2,
             (0x0 << 12) | 9, (0x3 << 12) | 4, (0x5 << 12) | 0b101]
    (tmp_path / "x.raw").write_bytes(b"% evt 3.0\n" + np.array(words, "<u2").tobytes())
    got = read_events(tmp_path / "x.raw")
    assert got.x.tolist() == [2, 4, 6] and got.y.tolist() == [7, 9, 9] and got.p.tolist() == [1, 0, 0]
    assert got.t_us.tolist() == [3 * 4096 + 5] * 3


def test_corrupted_evt3_time_high_names_the_byte(tmp_path):
    words = [(0x8 << 12) | 100, (0x6 << 12) | 5, (0x0 << 12) | 7, (0x2 << 12) | 9, (0x8 << 12) | 99, (0x2 << 12) | 9]
    (tmp_path / "x.raw").write_bytes(b"% evt 3.0\n" + np.array(words, "<u2").tobytes())
    with pytest.raises(DataError, match=r"time-high goes back from 100 to 99 at byte 18"):
        read_events(tmp_path / "x.raw")
    words[4] = 0x9 << 12  # a word type the specification does not define
    (tmp_path / "x.raw").write_bytes(b"% evt 3.0\n" + np.array(words, "<u2").tobytes())
    with pytest.raises(DataError, match=r"word type 0x9 at byte 18"):
        read_events(tmp_path / "x.raw")


@pytest.mark.parametrize("compression", ["NONE", "LZ4", "LZ4_HIGH", "ZSTD", "ZSTD_HIGH"])
def test_aedat4_decoder_gives_dv_processings_events_event_for_event(tmp_path, compression):
    """The project's decoder against iniVation's own reader, on files iniVation's writer made:
    every compression the format defines, and several packets (20k events)."""
    stream = camera_stream(n=20000, seed=6)
    write_aedat4(tmp_path / "rec.aedat4", stream, compression=compression)
    want = read_with_dv_processing(tmp_path / "rec.aedat4")
    got = read_events(tmp_path / "rec.aedat4")
    assert len(want) == len(stream) > 20000
    for ours, theirs in (("x", "x"), ("y", "y"), ("t_us", "timestamp"), ("p", "polarity")):
        np.testing.assert_array_equal(getattr(got, ours), want[theirs], err_msg=ours)


def test_aedat4_event_stream_is_found_behind_another_stream(tmp_path):
    stream = camera_stream(n=500, seed=8)
    write_aedat4(tmp_path / "rec.aedat4", stream, triggers_first=True)
    data = (tmp_path / "rec.aedat4").read_bytes()
    info = data[data.index(b"<dv"):data.index(b"</dv>")].decode()
    assert info.index('name="0"') < info.index("TRIG") < info.index('name="1"') < info.index("EVTS")
    pos, streams = 18 + int.from_bytes(data[14:18], "little"), set()
    while pos + 8 <= len(data) and 0 < (size := int.from_bytes(data[pos + 4:pos + 8], "little")) <= len(data) - pos:
        streams.add(int.from_bytes(data[pos:pos + 4], "little"))
        pos += 8 + size
    assert {0, 1} <= streams  # packets of both streams
    assert_same_events(read_events(tmp_path / "rec.aedat4"), stream)


def test_truncated_aedat4_names_the_byte_of_the_cut_packet(tmp_path):
    write_aedat4(tmp_path / "rec.aedat4", camera_stream(n=20000, seed=4))
    data = (tmp_path / "rec.aedat4").read_bytes()
    cut = len(data) * 2 // 3
    (tmp_path / "cut.aedat4").write_bytes(data[:cut])
    with pytest.raises(DataError) as info:
        read_events(tmp_path / "cut.aedat4")
    message = str(info.value)
    assert "cut.aedat4: corrupted IO header at byte 18: its data table position " in message
    assert "\n" not in message
    # Without the data table position (what a recording cut by a crash has: -1), the packet walk
    # names the packet that runs past the end.
    header_size = int.from_bytes(data[14:18], "little")
    table = data.index(int.to_bytes(int(message.split("position ")[1].split()[0]), 8, "little"), 18, 18 + header_size)
    no_table = data[:table] + (-1).to_bytes(8, "little", signed=True) + data[table + 8:cut]
    (tmp_path / "cut.aedat4").write_bytes(no_table)
    with pytest.raises(DataError) as info:
        read_events(tmp_path / "cut.aedat4")
    message = str(info.value)
    assert "cut.aedat4: truncated or corrupted at byte " in message and f"the end of the file at byte {cut}" in message
    offset = int(message.split("at byte ")[1].split(":")[0])
    assert 18 + header_size < offset < cut < offset + 8 + int.from_bytes(data[offset + 4:offset + 8], "little")


def test_files_that_hung_dv_processing_are_refused_in_seconds():
    """tests/fixtures/aedat4/: dv-processing's reader never returned on these (README there)."""
    from _bounded import BoundedWorker

    folder = Path(__file__).parent / "fixtures" / "aedat4"
    with BoundedWorker(preload=("e3dpsm.data.readers",)) as worker:
        for name in ("dv_hang_one_flip.aedat4", "dv_hang_three_flips.aedat4"):
            outcome = worker.call("e3dpsm.data.readers:read_events", folder / name, bound_s=30)
            assert outcome.kind == "refused", outcome
            assert outcome.detail == (f"DataError: {folder / name}: corrupted packet at byte 830: the lz4 data does "
                                      "not decompress (LZ4F_decompress failed with code: ERROR_decompressionFailed)")


@pytest.mark.parametrize("compression, module", [("LZ4", "lz4.frame"), ("ZSTD", "zstandard")])
def test_missing_decompressor_names_the_pip_extra(tmp_path, monkeypatch, compression, module):
    import sys

    write_aedat4(tmp_path / "r.aedat4", camera_stream(n=50, seed=1), compression=compression)
    monkeypatch.setitem(sys.modules, module, None)  # makes the import fail
    with pytest.raises(DataError, match=rf"needs the '{module}' package.*e3dpsm\[cameras\]"):
        read_events(tmp_path / "r.aedat4")


# `run` on every format ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def run_inputs(tmp_path_factory):
    """A 10-window stream as HDF5 and in every camera format, and the tiny exported graph."""
    folder = tmp_path_factory.mktemp("run_formats")
    x, y, t, p = synthetic_stream(seed=7)
    order = np.lexsort((x, p, y, t))  # the order EVT 3.0 vectors keep within one (t, y, p)
    stream = EventStream(x[order].astype(np.int32), y[order].astype(np.int32), t[order], p[order].astype(np.uint8))
    uniq = np.unique(np.stack([stream.t_us, stream.y, stream.p, stream.x], 1), axis=0, return_index=True)[1]
    keep = np.sort(uniq)
    stream = EventStream(stream.x[keep], stream.y[keep], stream.t_us[keep], stream.p[keep])
    write_events_h5(folder / "events.h5", stream)
    for name, encode in ENCODERS.items():
        (folder / name).write_bytes(encode(stream))
    write_aedat4(folder / "events.aedat4", stream) if _has_dv() else None
    graph = exported_tiny(str(tmp_path_factory.getbasetemp()))[1]
    return folder, graph


def _has_dv() -> bool:
    try:
        import dv_processing  # noqa: F401
    except ImportError:
        return False
    return True


def run_csv(graph, events, out) -> tuple[int, str]:
    code = main(["run", "--model", str(graph), "--events", str(events), "--out", str(out), "--threads", "1",
                 "--chunk-events", "700", "--no-progress"])
    return code, out.read_text() if out.exists() else ""


@pytest.mark.parametrize("name", [*ENCODERS, "events.aedat4"])
def test_run_poses_on_each_format_equal_those_on_the_hdf5(run_inputs, tmp_path, name):
    folder, graph = run_inputs
    if not (folder / name).exists():
        pytest.skip("dv-processing (pip extra cameras) is not installed")
    code_ref, want = run_csv(graph, folder / "events.h5", tmp_path / "ref.csv")
    code, got = run_csv(graph, folder / name, tmp_path / "got.csv")
    assert code_ref == 0 and code == 0
    assert got == want and len(want.splitlines()) >= 9  # byte-identical CSV: same poses, same decimals
    report = json.loads((tmp_path / "got.report.json").read_text())
    assert report["sensor_hw"] == [480, 640] and report["config"]["events"] == str(folder / name)


@pytest.mark.parametrize("name", [*ENCODERS, "events.aedat4"])
def test_run_on_a_truncated_file_fails_with_one_line_and_writes_nothing(run_inputs, tmp_path, capsys, name):
    folder, graph = run_inputs
    if not (folder / name).exists():
        pytest.skip("dv-processing (pip extra cameras) is not installed")
    data = (folder / name).read_bytes()
    (tmp_path / name).write_bytes(data[: len(data) // 2 | 1])  # odd length: mid-record for every format
    code, _ = run_csv(graph, tmp_path / name, tmp_path / "poses.csv")
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "byte" in err and name in err
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # no CSV, no report, no temporary
