"""Prophesee RAW (EVT 2.0, EVT 3.0) and DAT files, decoded with numpy.

Written from Prophesee's public specifications (docs.prophesee.ai, "Data Encoding Formats":
evt2.html, evt3.html; "File Formats": raw.html, dat.html). Why not a library: expelliarmus
1.1.12 reads EVT 3.0 timestamps wrong (its own EVT 3.0 writer's output comes back with
timestamps 4096 us off) and reads no sensor size; evlib 0.13.2 decodes the same EVT 3.0
file differently again, cannot read a DAT file expelliarmus wrote, and pulls in polars,
pyarrow and pandera, too much for the torch-free device runtime. Neither names the byte
where a damaged file breaks. The decoders below are vectorised (no per-event Python loop).

Header: ASCII lines starting with '%', ended by '% end' (newer files) or by the first line
that does not start with '%'. RAW sensor size: `% format EVT3;height=H;width=W` or
`% geometry WxH`; DAT: `% Width W` and `% Height H`.

Timestamps: microseconds as the camera counted them (from camera start). EVT 2.0 carries
34 bits, EVT 3.0 24 bits (the decoder unrolls the 16.7 s wrap of its high part), DAT 32 bits
(a recording longer than 71.6 min wraps; DAT cannot say so, so it is not unrolled).
Events before the first time-high word (and, in EVT 3.0, before the first row address)
have no defined time or row and are dropped, as the specification says decoding starts there.
Triggers and vendor extension words (EXT_TRIGGER, OTHERS, CONTINUED) are skipped.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from e3dpsm.errors import DataError

Columns = dict[str, np.ndarray]
HeaderInfo = tuple[list[str], int]

# EVT 2.0 word types (bits 31..28 of a 32-bit little-endian word)
EVT2_CD_OFF, EVT2_CD_ON, EVT2_TIME_HIGH = 0x0, 0x1, 0x8
EVT2_SKIPPED = (0xA, 0xE, 0xF)  # EXT_TRIGGER, OTHERS, CONTINUED
# EVT 3.0 word types (bits 15..12 of a 16-bit little-endian word)
EVT3_ADDR_Y, EVT3_ADDR_X, EVT3_VECT_BASE_X, EVT3_VECT_12, EVT3_VECT_8 = 0x0, 0x2, 0x3, 0x4, 0x5
EVT3_TIME_LOW, EVT3_CONTINUED_4, EVT3_TIME_HIGH = 0x6, 0x7, 0x8
EVT3_HIGH_RANGE = 1 << 12
EVT3_SKIPPED = (EVT3_CONTINUED_4, 0xA, 0xE, 0xF)  # + EXT_TRIGGER, OTHERS, CONTINUED_12
DAT_CD_TYPES = (0x00, 0x0C)  # Event2d, EventCd
DAT_EVENT_SIZE = 8


def read_header(data: bytes, path: Path) -> HeaderInfo:
    """The '%' header lines (without '% ') and the byte offset where binary data starts."""
    lines, pos = [], 0
    # "% " (not a bare "%"): a binary word may well start with the byte 0x25
    while data[pos:pos + 2] == b"% ":
        end = data.find(b"\n", pos)
        if end < 0:
            raise DataError(f"{path}: header line at byte {pos} has no end (truncated header)")
        line = data[pos + 2:end].decode("latin-1").strip()
        pos = end + 1
        if line == "end":
            break
        lines.append(line)
    return lines, pos


def _header_value(lines: list[str], key: str) -> str | None:
    for line in lines:
        name, _, value = line.partition(" ")
        if name.lower() == key.lower():
            return value.strip()
    return None


def raw_encoding_and_size(lines: list[str], path: Path) -> tuple[str, tuple[int, int] | None]:
    """('evt2' | 'evt3', (height, width) or None) from a RAW header."""
    fmt, hw = _header_value(lines, "format"), None
    if fmt is not None:  # newer files: "% format EVT3;height=720;width=1280"
        name, *options = fmt.split(";")
        opts = dict(o.split("=", 1) for o in options if "=" in o)
        encoding = {"EVT2": "evt2", "EVT3": "evt3"}.get(name.strip().upper())
        if "height" in opts and "width" in opts:
            hw = sensor_size(opts["height"], opts["width"], f"% format {fmt}", path)
    else:  # older files: "% evt 3.0"
        encoding = {"2.0": "evt2", "3.0": "evt3"}.get((_header_value(lines, "evt") or "").strip())
        fmt = _header_value(lines, "evt")
    if encoding is None:
        found = f"'{fmt}'" if fmt else "no '% format' or '% evt' line"
        raise DataError(f"{path}: unsupported RAW encoding ({found}); supported: EVT 2.0, EVT 3.0")
    geometry = _header_value(lines, "geometry")  # "% geometry 640x480"
    if hw is None and geometry:
        w, _, h = geometry.lower().partition("x")
        hw = sensor_size(h, w, f"% geometry {geometry}", path)
    return encoding, hw


def sensor_size(height: str, width: str, line: str, path: Path) -> tuple[int, int]:
    """(height, width) from header text; positive integers or DataError naming the line."""
    try:
        hw = (int(height), int(width))
    except ValueError:
        hw = (0, 0)
    if min(hw) <= 0:
        raise DataError(f"{path}: header line {line!r} does not state a sensor size in positive whole numbers")
    return hw


def read_raw(path: str | os.PathLike) -> tuple[Columns, tuple[int, int] | None]:
    """Decode a Prophesee RAW file (EVT 2.0 or EVT 3.0, as its header says)."""
    path = Path(path)
    data = path.read_bytes()
    lines, start = read_header(data, path)
    encoding, hw = raw_encoding_and_size(lines, path)
    decode = decode_evt2 if encoding == "evt2" else decode_evt3
    return decode(data, start, path), hw


def _words(data: bytes, start: int, size: int, path: Path, what: str) -> np.ndarray:
    body = len(data) - start
    whole = body - body % size
    if whole != body:
        raise DataError(
            f"{path}: truncated: the {what} record at byte {start + whole} needs {size} bytes, the file ends at "
            f"byte {len(data)}"
        )
    return np.frombuffer(data, dtype=f"<u{size}", offset=start, count=whole // size)


def _last_index(mask: np.ndarray) -> np.ndarray:
    """For each position, the index of the last True at or before it (-1 before the first)."""
    idx = np.where(mask, np.arange(mask.size), -1)
    return np.maximum.accumulate(idx) if idx.size else idx


def _unknown_word(types: np.ndarray, known: tuple[int, ...], start: int, size: int, path: Path, what: str) -> None:
    bad = np.flatnonzero(~np.isin(types, known))
    if bad.size:
        raise DataError(
            f"{path}: corrupted {what} data: word type 0x{int(types[bad[0]]):X} at byte {start + size * int(bad[0])} "
            f"is not in the specification ({bad.size} such words)"
        )


def decode_evt2(data: bytes, start: int, path: Path) -> Columns:
    words = _words(data, start, 4, path, "EVT 2.0").astype(np.uint64)
    types = (words >> 28).astype(np.uint8)
    _unknown_word(types, (EVT2_CD_OFF, EVT2_CD_ON, EVT2_TIME_HIGH, *EVT2_SKIPPED), start, 4, path, "EVT 2.0")
    last_high = _last_index(types == EVT2_TIME_HIGH)
    cd = ((types == EVT2_CD_OFF) | (types == EVT2_CD_ON)) & (last_high >= 0)
    w = words[cd]
    high = words[last_high[cd]] & 0x0FFFFFFF  # bits 27..0: timestamp bits 33..6
    return {
        "x": ((w >> 11) & 0x7FF).astype(np.int32),
        "y": (w & 0x7FF).astype(np.int32),
        "t": ((high << 6) | ((w >> 22) & 0x3F)).astype(np.int64),
        "p": types[cd].astype(np.uint8),  # CD_ON = 1, CD_OFF = 0
    }


def decode_evt3(data: bytes, start: int, path: Path) -> Columns:
    words = _words(data, start, 2, path, "EVT 3.0").astype(np.int64)
    types = words >> 12
    known = (EVT3_ADDR_Y, EVT3_ADDR_X, EVT3_VECT_BASE_X, EVT3_VECT_12, EVT3_VECT_8, EVT3_TIME_LOW, EVT3_TIME_HIGH,
             *EVT3_SKIPPED)
    _unknown_word(types, known, start, 2, path, "EVT 3.0")
    value = words & 0xFFF

    # Time: 12 high bits (TIME_HIGH) and 12 low bits (TIME_LOW), each a register holding its
    # last value. The high part wraps every 2^24 us: a fall by more than half its range is one
    # more wrap; a smaller fall is damage (Metavision calls it NonMonotonicTimeHigh).
    is_high = types == EVT3_TIME_HIGH
    highs = value[is_high]
    fall = -np.diff(highs)
    bad = np.flatnonzero((fall > 0) & (fall <= EVT3_HIGH_RANGE // 2))
    if bad.size:
        at = start + 2 * int(np.flatnonzero(is_high)[bad[0] + 1])
        raise DataError(f"{path}: corrupted EVT 3.0 data: time-high goes back from {highs[bad[0]]} to "
                        f"{highs[bad[0] + 1]} at byte {at}")
    wraps = np.concatenate([[0], np.cumsum(fall > EVT3_HIGH_RANGE // 2)]) if highs.size else highs
    high_full = np.zeros(words.size, np.int64)
    high_full[is_high] = (wraps << 12) + highs
    last_high, last_low = _last_index(is_high), _last_index(types == EVT3_TIME_LOW)
    t_word = (high_full[np.maximum(last_high, 0)] << 12) | np.where(last_low >= 0, value[np.maximum(last_low, 0)], 0)
    last_y = _last_index(types == EVT3_ADDR_Y)
    y_word = value[np.maximum(last_y, 0)] & 0x7FF
    defined = (last_high >= 0) & (last_y >= 0)

    # Single events: x and polarity in the word.
    single = np.flatnonzero((types == EVT3_ADDR_X) & defined)
    # Vectors: VECT_BASE_X sets a base x and polarity; each VECT_12 / VECT_8 marks events at
    # base + bit for its set bits, then moves the base on by 12 / 8.
    is_base = types == EVT3_VECT_BASE_X
    step = np.where(types == EVT3_VECT_12, 12, np.where(types == EVT3_VECT_8, 8, 0))
    before = np.cumsum(step) - step  # vector steps before each word
    last_base = _last_index(is_base)
    vec = np.flatnonzero((step > 0) & defined & (last_base >= 0))
    base_word = last_base[vec]
    base_x = (value[base_word] & 0x7FF) + before[vec] - before[base_word]
    mask = np.where(step[vec] == 12, value[vec], value[vec] & 0xFF)
    rows, bits = np.nonzero((mask[:, None] >> np.arange(12)) & 1)

    word = np.concatenate([single, vec[rows]])
    x = np.concatenate([value[single] & 0x7FF, base_x[rows] + bits])
    p = np.concatenate([(value[single] >> 11) & 1, (value[base_word[rows]] >> 11) & 1])
    order = np.lexsort((np.concatenate([np.zeros(single.size, np.int64), bits]), word))  # file order
    word = word[order]
    return {
        "x": x[order].astype(np.int32), "y": y_word[word].astype(np.int32),
        "t": t_word[word], "p": p[order].astype(np.uint8),
    }


def read_dat(path: str | os.PathLike) -> tuple[Columns, tuple[int, int] | None]:
    """Decode a Prophesee DAT file of CD events (version 2: 32-bit time, x 14 bits, y 14 bits, p 4 bits)."""
    path = Path(path)
    data = path.read_bytes()
    lines, start = read_header(data, path)
    version = _header_value(lines, "Version")
    if version not in (None, "2"):
        raise DataError(f"{path}: DAT version {version} is not supported; expected version 2")
    if len(data) < start + 2:
        raise DataError(f"{path}: truncated: the event type and size bytes at byte {start} are missing")
    ev_type, ev_size = data[start], data[start + 1]
    if ev_type not in DAT_CD_TYPES or ev_size != DAT_EVENT_SIZE:
        raise DataError(
            f"{path}: DAT event type {ev_type} of size {ev_size} at byte {start} is not a CD event "
            f"(expected type 12 or 0, size 8)"
        )
    records = _words(data, start + 2, 8, path, "DAT event")
    t, d = records & 0xFFFFFFFF, records >> 32
    hw = None
    width, height = _header_value(lines, "Width"), _header_value(lines, "Height")
    if width and height:
        hw = sensor_size(height, width, f"% Width {width} / % Height {height}", path)
    return {
        "x": (d & 0x3FFF).astype(np.int32), "y": ((d >> 14) & 0x3FFF).astype(np.int32),
        "t": t.astype(np.int64), "p": (d >> 28).astype(np.uint8),
    }, hw
