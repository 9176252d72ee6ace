"""iniVation AEDAT4 recordings, decoded in the project; the dv:// network stream (e3dpsm/data/live.py)
carries the same IO header and packets and goes through the same functions.

Why not dv-processing's `MonoCameraRecording`, which read these files before: on a file with a
few bytes changed inside its packets, `getNextEventBatch()` can spin forever in C++ holding
the GIL (3 of 4 such files did), which no Python deadline can interrupt. This decoder is
bounded by construction: every offset and length is checked against its buffer before it is
followed, the packet walk moves on by at least 9 bytes a step, and a packet may decompress to
at most MAX_EXPANSION times its size. It is also faster (docs/cameras.md, measured side by
side by benchmarks/bench_camera_readers.py). dv-processing stays the tests' independent
writer, and the decoded events are checked against its reader event for event.

Layout (AEDAT 4.0, https://docs.inivation.com/software/software-advanced-usage/file-formats/aedat-4.0.html):
the 14-byte magic "#!AER-DAT4.0\\r\\n"; an int32 size and an IOHeader FlatBuffer (identifier
"IOHE": field 0 compression, int32: 0 none, 1/2 LZ4, 3/4 Zstd; field 1 dataTablePosition,
int64, -1 when absent; field 2 infoNode, an XML string naming each stream: its id, type
identifier ("EVTS" for events) and sensor size sizeX/sizeY); then packets: int32 stream id,
int32 size, payload. The payload, compressed as a whole (one LZ4 or Zstd frame) unless the
compression is none, is a size-prefixed FlatBuffer; an event packet (identifier "EVTS")
holds in field 0 a vector of 16-byte Event structs: int64 timestamp (us since the Unix
epoch), int16 x, int16 y, bool polarity, 3 bytes padding. Packets end at the FileDataTable
(an index of the packets, not needed to read them) or at the end of the file.
"""
from __future__ import annotations

import os
import re
import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from e3dpsm.data.formats import require
from e3dpsm.data.formats.flatbuffer import FlatBufferError, root_table, scalar, string, vector
from e3dpsm.errors import DataError

MAGIC = b"#!AER-DAT4.0\r\n"
EVENT_DTYPE = np.dtype({"names": ["t", "x", "y", "p"], "formats": ["<i8", "<i2", "<i2", "u1"],
                        "offsets": [0, 8, 10, 12], "itemsize": 16})
COMPRESSIONS = {0: "none", 1: "lz4", 2: "lz4", 3: "zstd", 4: "zstd"}  # LZ4_HIGH, ZSTD_HIGH decode alike
# LZ4 cannot expand data by more than ~255x; Zstd can, but event packets (timestamps,
# coordinates) compress a few-fold. A packet claiming more is refused, not allocated.
MAX_EXPANSION = 1024
PACKET_HEADER = struct.Struct("<ii")  # stream id, payload size


@dataclass(frozen=True)
class IOHeader:
    compression: str  # a value of COMPRESSIONS
    data_table_position: int  # -1: no data table
    event_stream: int  # id of the first event stream
    sensor_hw: tuple[int, int] | None


def parse_io_header(buf: bytes, label: str, at: int) -> IOHeader:
    """The IO header FlatBuffer `buf` (found at byte `at` of `label`), its event stream located."""
    try:
        table = root_table(buf, b"IOHE")
        code = scalar(table, 0, "<i", 0)
        data_table = scalar(table, 1, "<q", -1)
        info = string(table, 2)
    except FlatBufferError as exc:
        raise DataError(f"{label}: corrupted IO header at byte {at + exc.offset}: {exc}") from exc
    if code not in COMPRESSIONS:
        raise DataError(f"{label}: the IO header at byte {at} names compression {code}; AEDAT 4.0 defines 0-4")
    stream, hw = _event_stream(info or b"", label, at)
    return IOHeader(COMPRESSIONS[code], data_table, stream, hw)


def _event_stream(info: bytes, label: str, at: int) -> tuple[int, tuple[int, int] | None]:
    """(id, sensor (height, width) or None) of the lowest-numbered "EVTS" stream in the XML."""
    try:
        root = ET.fromstring(info.rstrip(b"\0"))
    except ET.ParseError as exc:
        raise DataError(f"{label}: the IO header at byte {at} holds no valid stream description (XML: {exc})") from exc
    found = {}
    for node in root.iterfind("./node[@name='outInfo']/node"):
        attrs = {a.get("key"): (a.text or "").strip() for a in node.iterfind("attr")}
        if attrs.get("typeIdentifier") == "EVTS" and re.fullmatch(r"[0-9]{1,9}", node.get("name") or ""):
            found[int(node.get("name"))] = node
    if not found:
        raise DataError(f"{label}: no event stream (no 'EVTS' output in the IO header's stream description)")
    stream = min(found)
    size = {a.get("key"): (a.text or "").strip() for a in found[stream].iterfind("./node[@name='info']/attr")}
    if "sizeX" not in size or "sizeY" not in size:
        return stream, None
    try:
        hw = (int(size["sizeY"]), int(size["sizeX"]))
    except ValueError:
        hw = (0, 0)
    if min(hw) <= 0 or max(hw) > 1 << 15:
        raise DataError(f"{label}: event stream {stream} states sensor size {size['sizeX']} x {size['sizeY']}, "
                        "expected positive integers")
    return stream, hw


def decompress(payload: bytes | memoryview, compression: str) -> bytes | memoryview:
    """A packet's payload decompressed, at most MAX_EXPANSION times its size (ValueError if not)."""
    if compression == "none":
        return payload
    limit = MAX_EXPANSION * len(payload) + 4096
    try:
        out, rest = (_lz4 if compression == "lz4" else _zstd)(payload, limit)
    except (DataError, ValueError):  # DataError: the decompression package is missing
        raise
    except Exception as exc:  # lz4 raises RuntimeError, zstandard ZstdError: both name the damage
        raise ValueError(f"the {compression} data does not decompress ({str(exc).splitlines()[0]})") from exc
    if rest:
        raise ValueError(f"{rest} bytes follow the {compression} frame")
    return out


def _lz4(payload: bytes | memoryview, limit: int) -> tuple[bytes, int]:
    """(decompressed, bytes left over). LZ4 expands at most ~255x; a frame header's own
    content size (DV leaves it out) is checked before anything is allocated."""
    lz4 = require("lz4.frame", "reading an LZ4-compressed AEDAT4 stream")
    if lz4.get_frame_info(payload)["content_size"] > limit:
        raise ValueError(f"its LZ4 frame claims more than {MAX_EXPANSION}x its size")
    out, used = lz4.decompress(payload, return_bytes_read=True)
    return out, len(payload) - used


def _zstd(payload: bytes | memoryview, limit: int) -> tuple[bytes, int]:
    """(decompressed, bytes left over), reading at most `limit` bytes out."""
    zstd = require("zstandard", "reading a Zstd-compressed AEDAT4 stream")
    size = zstd.get_frame_parameters(payload).content_size
    if size == zstd.CONTENTSIZE_UNKNOWN:  # measured by reading, in bounded steps
        reader, total = zstd.ZstdDecompressor().stream_reader(payload, read_across_frames=False), 0
        while total <= limit and (part := reader.read(1 << 20)):  # at most limit / 1 MiB + 2 reads
            total += len(part)
        if total > limit:
            raise ValueError(f"it expands more than {MAX_EXPANSION}x")
    elif size > limit:  # the frame's own size, which the decoder holds it to
        raise ValueError(f"its Zstd frame claims more than {MAX_EXPANSION}x its size")
    # Now known to fit: decoded by a decoder that stops at the frame's end and keeps what
    # follows, so that it is counted (the measuring reader goes on into a next frame). An
    # unsized frame is thus decoded twice; dv-processing writes the size, so its files are not.
    stream = zstd.ZstdDecompressor().decompressobj()
    out = stream.decompress(payload)
    return out, len(stream.unused_data)


def decode_event_packet(payload: bytes | memoryview, compression: str) -> np.ndarray:
    """The events of one packet as a structured array (a view of the decompressed buffer).

    Raises ValueError (with what is wrong) on a damaged packet."""
    buf = decompress(payload, compression)
    if len(buf) < 4:
        raise ValueError(f"{len(buf)} bytes decompressed, too few for a FlatBuffer")
    (size,) = struct.unpack_from("<I", buf, 0)
    if size != len(buf) - 4:
        raise ValueError(f"its FlatBuffer declares {size} bytes, {len(buf) - 4} decompressed")
    try:
        table = root_table(memoryview(buf)[4:], b"EVTS")
        found = vector(table, 0, EVENT_DTYPE.itemsize)
    except FlatBufferError as exc:
        raise ValueError(f"{exc} (byte {4 + exc.offset} of the decompressed packet)") from exc
    if found is None:
        return np.zeros(0, EVENT_DTYPE)
    start, count = found
    return np.frombuffer(buf, EVENT_DTYPE, count=count, offset=4 + start)


def read_aedat4(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], tuple[int, int] | None]:
    """Events of the first event stream of an AEDAT4 file, and the sensor (height, width)."""
    path = Path(path)
    data = path.read_bytes()
    header, end = _file_header(data, str(path))
    pos, packets = len(MAGIC) + 4 + struct.unpack_from("<i", data, len(MAGIC))[0], []
    while pos < end:  # every step moves on by 8 + size >= 9 bytes
        if pos + PACKET_HEADER.size > end:
            raise DataError(f"{path}: truncated or corrupted at byte {pos}: {end - pos} bytes left before "
                            f"{_end_name(header, end)} at byte {end}, too few for a packet header")
        stream, size = PACKET_HEADER.unpack_from(data, pos)
        body = pos + PACKET_HEADER.size
        if stream < 0 or size <= 0 or body + size > end:
            raise DataError(f"{path}: truncated or corrupted at byte {pos}: the packet there (stream {stream}, "
                            f"{size} bytes) runs past {_end_name(header, end)} at byte {end}")
        if stream == header.event_stream:
            try:
                packets.append(decode_event_packet(memoryview(data)[body:body + size], header.compression))
            except ValueError as exc:
                raise DataError(f"{path}: corrupted packet at byte {pos}: {exc}") from exc
        pos = body + size
    return columns(packets), header.sensor_hw


def columns(packets: list[np.ndarray]) -> dict[str, np.ndarray]:
    """x, y, t, p of the packets' events, in order (filled in place: a tenth of the time of
    casting each packet and concatenating)."""
    n = sum(len(events) for events in packets)
    out = {"x": np.empty(n, np.int32), "y": np.empty(n, np.int32), "t": np.empty(n, np.int64),
           "p": np.empty(n, np.uint8)}
    lo = 0
    for events in packets:
        hi = lo + len(events)
        out["x"][lo:hi], out["y"][lo:hi], out["t"][lo:hi] = events["x"], events["y"], events["t"]
        np.not_equal(events["p"], 0, out=out["p"][lo:hi].view(bool))  # a bool byte: any non-zero is true
        lo = hi
    return out


def _file_header(data: bytes, label: str) -> tuple[IOHeader, int]:
    """The IO header and the byte where packets end (the data table, or the end of the file)."""
    if not data.startswith(MAGIC):
        raise DataError(f"{label}: not an AEDAT4 file: no {MAGIC!r} at byte 0")
    at = len(MAGIC)
    if at + 4 > len(data):
        raise DataError(f"{label}: truncated: the IO header size at byte {at} is missing (file ends at byte "
                        f"{len(data)})")
    (size,) = struct.unpack_from("<i", data, at)
    if size <= 0 or at + 4 + size > len(data):
        raise DataError(f"{label}: truncated or corrupted IO header at byte {at} (declares {size} bytes, file ends "
                        f"at byte {len(data)})")
    header = parse_io_header(data[at + 4:at + 4 + size], label, at + 4)
    first, table = at + 4 + size, header.data_table_position
    if table == -1:
        return header, len(data)
    if not first <= table <= len(data):
        raise DataError(f"{label}: corrupted IO header at byte {at + 4}: its data table position {table} lies outside "
                        f"the packets (bytes {first} to {len(data)})")
    return header, table


def _end_name(header: IOHeader, end: int) -> str:
    return "the end of the file" if header.data_table_position != end else "the data table"
