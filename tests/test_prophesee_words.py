"""e3dpsm/data/formats/prophesee.py word by word, against Prophesee's public specifications
(docs.prophesee.ai, "Data Encoding Formats": evt2.html, evt3.html; "File Formats": raw.html,
dat.html): each case a handful of words written by hand from the spec, with the events the
spec says they mean. The round trips of whole recordings are tests/test_formats.py."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from e3dpsm.data.formats import prophesee
from e3dpsm.errors import DataError


def _header(*lines: str) -> bytes:
    return "".join(f"% {line}\n" for line in lines).encode("ascii")


def _evt2(*words: int) -> bytes:
    return struct.pack(f"<{len(words)}I", *words)


def _evt3(*words: int) -> bytes:
    return struct.pack(f"<{len(words)}H", *words)


def _cd2(p: int, t: int, x: int, y: int) -> int:  # EVT 2.0 CD_OFF / CD_ON
    return (p << 28) | ((t & 0x3F) << 22) | (x << 11) | y


def _high2(t: int) -> int:  # EVT 2.0 EVT_TIME_HIGH: timestamp bits 33..6
    return (0x8 << 28) | (t >> 6)


def _w3(kind: int, value: int) -> int:  # EVT 3.0: type in bits 15..12, 12 bits of value
    return (kind << 12) | value


def _read(tmp_path: Path, name: str, content: bytes):
    path = tmp_path / name
    path.write_bytes(content)
    columns, hw = (prophesee.read_dat if name.endswith(".dat") else prophesee.read_raw)(path)
    return [tuple(int(columns[k][i]) for k in ("t", "x", "y", "p")) for i in range(len(columns["t"]))], hw


# ---- header -------------------------------------------------------------------------------------------
def test_the_header_ends_at_its_end_line_even_when_data_starts_with_a_percent_sign() -> None:
    """"% end" ends the header (raw.html); the binary data after it may well begin with the
    bytes '%' ' ' (0x25 0x20), which must not be read as one more header line."""
    body = struct.pack("<I", 0x00AA2025)
    data = _header("camera_integrator_name Prophesee", "format EVT3;height=4;width=6", "end") + body
    lines, start = prophesee.read_header(data, Path("f.raw"))
    assert lines == ["camera_integrator_name Prophesee", "format EVT3;height=4;width=6"]
    assert data[start:] == body
    older = _header("evt 2.0") + b"\x01\x02"  # older files: the first line without '% ' ends it
    assert prophesee.read_header(older, Path("f.raw")) == (["evt 2.0"], len(older) - 2)


def test_a_header_line_without_its_end_names_the_byte() -> None:
    with pytest.raises(DataError) as info:
        prophesee.read_header(_header("evt 3.0") + b"% geometry 640", Path("cut.raw"))
    assert str(info.value) == "cut.raw: header line at byte 10 has no end (truncated header)"


@pytest.mark.parametrize("lines, expected", [
    (["format EVT3;height=720;width=1280"], ("evt3", (720, 1280))),
    (["format evt2;width=640;height=480"], ("evt2", (480, 640))),
    (["format EVT3;height=720;width=1280;note=a=b"], ("evt3", (720, 1280))),  # a value may hold '='
    (["format EVT3;height=720", "geometry 640x480"], ("evt3", (480, 640))),  # half a size: the geometry line
    (["format EVT3"], ("evt3", None)),
    (["evt 3.0", "geometry 1280x720"], ("evt3", (720, 1280))),
    (["Evt 2.0"], ("evt2", None)),  # keys are case-blind
    (["integrator Prophesee", "evt 2.0"], ("evt2", None)),
])
def test_raw_encoding_and_sensor_size_from_the_header(lines, expected) -> None:
    assert prophesee.raw_encoding_and_size(lines, Path("f.raw")) == expected


@pytest.mark.parametrize("lines, message", [
    (["evt 4.0"], "f.raw: unsupported RAW encoding ('4.0'); supported: EVT 2.0, EVT 3.0"),
    (["format EVT4;height=1;width=1"], "f.raw: unsupported RAW encoding ('EVT4;height=1;width=1'); supported: "
                                       "EVT 2.0, EVT 3.0"),
    (["integrator Prophesee"], "f.raw: unsupported RAW encoding (no '% format' or '% evt' line); supported: "
                               "EVT 2.0, EVT 3.0"),
    (["format EVT3;height=0;width=5"], "f.raw: header line '% format EVT3;height=0;width=5' does not state a sensor "
                                       "size in positive whole numbers"),
    (["evt 3.0", "geometry 640xabc"], "f.raw: header line '% geometry 640xabc' does not state a sensor size in "
                                      "positive whole numbers"),
])
def test_a_header_that_states_no_usable_encoding_or_size_says_which_line(lines, message) -> None:
    with pytest.raises(DataError) as info:
        prophesee.raw_encoding_and_size(lines, Path("f.raw"))
    assert str(info.value) == message


def test_a_sensor_size_is_two_positive_whole_numbers() -> None:
    assert prophesee.sensor_size("1", "2", "l", Path("f")) == (1, 2)
    for height, width in (("0", "2"), ("2", "-1"), ("x", "2"), ("2.5", "3")):
        with pytest.raises(DataError, match="does not state a sensor size"):
            prophesee.sensor_size(height, width, "l", Path("f"))


def test_last_index_is_the_explicit_loops() -> None:
    mask = np.array([False, True, False, False, True, False])
    expected, last = [], -1
    for i, value in enumerate(mask):
        last = i if value else last
        expected.append(last)
    assert prophesee._last_index(mask).tolist() == expected == [-1, 1, 1, 1, 4, 4]
    assert prophesee._last_index(np.zeros(0, bool)).size == 0


# ---- EVT 2.0 ------------------------------------------------------------------------------------------
def test_evt2_events_take_their_time_high_and_skip_triggers_and_extension_words(tmp_path) -> None:
    """A time-high as the very first word defines the time of what follows; EXT_TRIGGER (0xA),
    OTHERS (0xE) and CONTINUED (0xF) words carry no CD event."""
    t0 = (5 << 6) + 9
    words = [_high2(t0), _cd2(1, t0, 3, 4), (0xA << 28) | 7, (0xE << 28) | 1, (0xF << 28) | 2,
             _cd2(0, t0 + 1, 639, 479), _high2(1 << 33), _cd2(1, 1 << 33, 0, 0)]
    events, hw = _read(tmp_path, "a.raw", _header("evt 2.0", "geometry 640x480") + _evt2(*words))
    assert events == [(t0, 3, 4, 1), (t0 + 1, 639, 479, 0), (1 << 33, 0, 0, 1)] and hw == (480, 640)


def test_evt2_events_before_the_first_time_high_are_dropped(tmp_path) -> None:
    events, _ = _read(tmp_path, "b.raw", _header("evt 2.0") + _evt2(_cd2(1, 0, 1, 1), _high2(64), _cd2(0, 65, 2, 2)))
    assert events == [(65, 2, 2, 0)]


@pytest.mark.parametrize("name, body, message", [
    ("c.raw", _evt2(_high2(64), (0xB << 28) | 5, (0x3 << 28)),
     "corrupted EVT 2.0 data: word type 0xB at byte 14 is not in the specification (2 such words)"),
    ("d.raw", _evt2(_high2(64)) + b"\x01\x02", "truncated: the EVT 2.0 record at byte 14 needs 4 bytes, the file "
                                                "ends at byte 16"),
])
def test_evt2_damage_names_the_byte(tmp_path, name, body, message) -> None:
    """The header "% evt 2.0\\n" is 10 bytes: word k starts at byte 10 + 4 k."""
    with pytest.raises(DataError) as info:
        _read(tmp_path, name, _header("evt 2.0") + body)
    assert str(info.value) == f"{tmp_path / name}: {message}"


# ---- EVT 3.0 ------------------------------------------------------------------------------------------
Y, X, BASE, V12, V8, LOW, C4, HIGH = 0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x8


def _raw3(*words: int) -> bytes:
    return _header("evt 3.0") + _evt3(*words)


def test_evt3_time_is_its_high_and_low_registers(tmp_path) -> None:
    """A TIME_LOW as the first word of the file is a register like any other: the events after
    the first TIME_HIGH and ADDR_Y take it; before any TIME_LOW the low part is 0."""
    words = [_w3(LOW, 0x345), _w3(HIGH, 0x012), _w3(Y, 7), _w3(X, (1 << 11) | 20),
             _w3(LOW, 0x346), _w3(X, 21), _w3(HIGH, 0x013), _w3(X, 22)]
    events, _ = _read(tmp_path, "e.raw", _raw3(*words))
    assert events == [((0x012 << 12) | 0x345, 20, 7, 1), ((0x012 << 12) | 0x346, 21, 7, 0),
                      ((0x013 << 12) | 0x346, 22, 7, 0)]
    no_low, _ = _read(tmp_path, "f.raw", _raw3(_w3(HIGH, 3), _w3(Y, 1), _w3(X, 2)))
    assert no_low == [(3 << 12, 2, 1, 0)]


def test_evt3_drops_events_before_a_time_high_or_a_row(tmp_path) -> None:
    words = [_w3(Y, 1), _w3(X, 5), _w3(HIGH, 2), _w3(Y, 3), _w3(X, 6)]
    events, _ = _read(tmp_path, "g.raw", _raw3(_w3(HIGH, 1), _w3(X, 4), *words))
    assert events == [((1 << 12), 5, 1, 0), ((2 << 12), 6, 3, 0)]


def test_evt3_vectors_mark_a_bit_per_event_and_move_their_base(tmp_path) -> None:
    """VECT_BASE_X sets base x and polarity; VECT_12 marks base + i for each set bit i of its 12
    and moves the base on by 12, VECT_8 by 8 with 8 bits. A base set before the first time-high
    is still the register's value when a vector comes after it."""
    words = [_w3(BASE, (1 << 11) | 100), _w3(HIGH, 1), _w3(Y, 9), _w3(V8, 0b10000001), _w3(V12, 0b100000000011),
             _w3(V8, 0b1), _w3(X, 7), _w3(BASE, 40), _w3(V12, 0b10)]
    events, _ = _read(tmp_path, "h.raw", _raw3(*words))
    t = 1 << 12
    assert events == [(t, 100, 9, 1), (t, 107, 9, 1), (t, 108, 9, 1), (t, 109, 9, 1), (t, 119, 9, 1),
                      (t, 120, 9, 1), (t, 7, 9, 0), (t, 41, 9, 0)]


def test_evt3_skips_continued_triggers_and_extension_words(tmp_path) -> None:
    words = [_w3(HIGH, 1), _w3(Y, 2), _w3(C4, 0xF), _w3(0xA, 1), _w3(0xE, 2), _w3(0xF, 3), _w3(X, 4)]
    events, _ = _read(tmp_path, "i.raw", _raw3(*words))
    assert events == [(1 << 12, 4, 2, 0)]


def test_evt3_time_high_wraps_forward_and_a_repeat_is_no_fall(tmp_path) -> None:
    """The 12-bit time-high wraps every 2^24 us: a fall by more than half its range is one more
    wrap; the same value twice is no fall at all."""
    words = [_w3(HIGH, 0xFFE), _w3(HIGH, 0xFFE), _w3(Y, 0), _w3(X, 1), _w3(HIGH, 0x001), _w3(X, 2)]
    events, _ = _read(tmp_path, "j.raw", _raw3(*words))
    assert events == [(0xFFE << 12, 1, 0, 0), ((1 << 24) + (1 << 12), 2, 0, 0)]


@pytest.mark.parametrize("fall", [1, 1500, 2048])
def test_evt3_time_high_falling_by_half_its_range_or_less_is_damage(tmp_path, fall) -> None:
    """Word k starts at byte 10 + 2 k (the header "% evt 3.0\\n" is 10 bytes)."""
    words = [_w3(HIGH, 3000), _w3(Y, 0), _w3(X, 1), _w3(HIGH, 3000 - fall), _w3(X, 2), _w3(HIGH, 3005 - fall)]
    with pytest.raises(DataError) as info:
        _read(tmp_path, "k.raw", _raw3(*words))
    assert str(info.value).endswith(f"k.raw: corrupted EVT 3.0 data: time-high goes back from 3000 to "
                                    f"{3000 - fall} at byte 16")


def test_evt3_a_fall_just_over_half_the_range_is_a_wrap(tmp_path) -> None:
    events, _ = _read(tmp_path, "l.raw", _raw3(_w3(HIGH, 3000), _w3(HIGH, 3000 - 2049), _w3(Y, 0), _w3(X, 1)))
    assert events == [((1 << 24) + ((3000 - 2049) << 12), 1, 0, 0)]


def test_evt3_truncated_names_its_byte(tmp_path) -> None:
    with pytest.raises(DataError) as info:
        _read(tmp_path, "n.raw", _raw3(_w3(HIGH, 1), _w3(Y, 0)) + b"\x02")
    assert str(info.value).endswith("n.raw: truncated: the EVT 3.0 record at byte 14 needs 2 bytes, the file ends at "
                                    "byte 15")


def test_evt3_unknown_word_names_its_byte(tmp_path) -> None:
    with pytest.raises(DataError) as info:
        _read(tmp_path, "m.raw", _raw3(_w3(HIGH, 1), _w3(0x9, 0), _w3(0xB, 0), _w3(0x1, 0)))
    assert str(info.value).endswith("m.raw: corrupted EVT 3.0 data: word type 0x9 at byte 12 is not in the "
                                    "specification (3 such words)")


# ---- DAT ----------------------------------------------------------------------------------------------
def _dat(*records: tuple[int, int, int, int], header: tuple[str, ...] = ("Version 2",),
         kind: bytes = bytes([0x0C, 8])) -> bytes:
    return _header(*header) + kind + b"".join(struct.pack("<II", t, (p << 28) | (y << 14) | x)
                                              for t, x, y, p in records)


def test_dat_records_and_sensor_size(tmp_path) -> None:
    records = [(5, 16383, 0, 1), (2 ** 32 - 1, 0, 16383, 0)]
    events, hw = _read(tmp_path, "a.dat", _dat(*records, header=("Version 2", "Width 640", "Height 480")))
    assert events == records and hw == (480, 640)
    assert _read(tmp_path, "b.dat", _dat(*records, header=("Width 640",))) == (records, None)  # half a size
    assert _read(tmp_path, "c.dat", _dat(*records, header=())) == (records, None)  # no version line: version 2
    assert _read(tmp_path, "d.dat", _dat(header=("Version 2",))) == ([], None)  # type and size, no event yet
    events, _ = _read(tmp_path, "e.dat", _dat(*records, kind=bytes([0x00, 8])))  # Event2d, the older type
    assert events == records


@pytest.mark.parametrize("content, message", [
    (_dat(header=("Version 3",)), "DAT version 3 is not supported; expected version 2"),
    (_header("Version 2") + b"\x0c", "truncated: the event type and size bytes at byte 12 are missing"),
    (_dat(kind=bytes([5, 8])), "DAT event type 5 of size 8 at byte 12 is not a CD event (expected type 12 or 0, "
                               "size 8)"),
    (_dat(kind=bytes([12, 16])), "DAT event type 12 of size 16 at byte 12 is not a CD event (expected type 12 or 0, "
                                 "size 8)"),
    (_dat((1, 2, 3, 1)) + b"\x00" * 3, "truncated: the DAT event record at byte 22 needs 8 bytes, the file ends at "
                                        "byte 25"),
    (_dat(header=("Version 2", "Width 0", "Height 4")), "header line '% Width 0 / % Height 4' does not state a "
                                                        "sensor size in positive whole numbers"),
])
def test_dat_damage_is_one_line_naming_what_and_where(tmp_path, content, message) -> None:
    with pytest.raises(DataError) as info:
        _read(tmp_path, "bad.dat", content)
    assert str(info.value) == f"{tmp_path / 'bad.dat'}: {message}"
