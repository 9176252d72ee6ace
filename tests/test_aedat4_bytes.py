"""e3dpsm/data/formats/inivation.py on AEDAT 4.0 files laid out byte by byte after the format's
documentation (docs.inivation.com, "AEDAT 4.0": magic, int32 IO header size, IOHeader
FlatBuffer, packets of int32 stream id, int32 size, payload, an optional data table), with the
FlatBuffers built by Google's own Builder (tests/_flatbuffer_builders.py). Each boundary
is met exactly, then missed by one byte, and every refusal is compared whole: a message test
by pattern would pass a message wrapped in anything. (Files by dv-processing's own writer:
tests/test_formats.py.)"""
from __future__ import annotations

import dataclasses
import struct
import sys

import numpy as np
import pytest

from e3dpsm.data.formats import inivation
from e3dpsm.errors import DataError

pytest.importorskip("flatbuffers")
from _flatbuffer_builders import EVENTS, event_packet, io_header  # noqa: E402  (needs flatbuffers)

MAGIC = b"#!AER-DAT4.0\r\n"  # 14 bytes: the IO header's size is at byte 14, the header at 18


def _xml(*streams: tuple[str, str, dict[str, str]]) -> bytes:
    """An IO header's stream description: (node name, type identifier, info attributes)."""
    nodes = "".join(
        f'<node name="{name}" path="/outInfo/{name}/"><attr key="typeIdentifier" type="string">{kind}</attr>'
        f'<node name="info" path="/outInfo/{name}/info/">'
        + "".join(f'<attr key="{k}" type="int">{v}</attr>' for k, v in info.items()) + "</node></node>"
        for name, kind, info in streams)
    return f'<dv version="2.0"><node name="outInfo" path="/outInfo/">{nodes}</node></dv>'.encode()


SENSOR = {"sizeX": "346", "sizeY": "260"}
INFO = _xml(("7", "IMUS", {}), ("3", "EVTS", SENSOR))


def _file(packets: list[tuple[int, bytes]] = (), table: int | None = None, info: bytes = INFO,
          compression: int = 0, header: bytes | None = None) -> bytes:
    head = header if header is not None else io_header(compression, table, info)
    body = b"".join(struct.pack("<ii", stream, len(payload)) + payload for stream, payload in packets)
    return MAGIC + struct.pack("<i", len(head)) + head + body


def _read(tmp_path, data: bytes, name: str = "r.aedat4"):
    path = tmp_path / name
    path.write_bytes(data)
    return inivation.read_aedat4(path)


def _refused(tmp_path, data: bytes) -> str:
    path = tmp_path / "bad.aedat4"
    path.write_bytes(data)
    with pytest.raises(DataError) as info:
        inivation.read_aedat4(path)
    return str(info.value).removeprefix(f"{path}: ")


# ---- the file header --------------------------------------------------------------------------------------
def test_a_header_alone_is_a_recording_of_no_events(tmp_path) -> None:
    """The IO header may fill the file exactly: no packets, the sensor from the description."""
    columns, hw = _read(tmp_path, _file())
    assert hw == (260, 346) and all(len(columns[k]) == 0 for k in "xytp")


@pytest.mark.parametrize("data, message", [
    (b"#!AER-DAT3.1\r\n" + bytes(8), "not an AEDAT4 file: no b'#!AER-DAT4.0\\r\\n' at byte 0"),
    (MAGIC + b"\x05\0\0", "truncated: the IO header size at byte 14 is missing (file ends at byte 17)"),
    (MAGIC + struct.pack("<i", 5), "truncated or corrupted IO header at byte 14 (declares 5 bytes, file ends at byte 18)"),
    (MAGIC + struct.pack("<i", 0) + bytes(8), "truncated or corrupted IO header at byte 14 (declares 0 bytes, file ends "
                                              "at byte 26)"),
    (MAGIC + struct.pack("<i", -3) + bytes(8), "truncated or corrupted IO header at byte 14 (declares -3 bytes, file "
                                               "ends at byte 26)"),
])
def test_a_file_header_that_is_not_whole_names_the_byte(tmp_path, data, message) -> None:
    assert _refused(tmp_path, data) == message


def test_an_io_header_one_byte_longer_than_the_file_is_refused(tmp_path) -> None:
    data = _file()
    size = len(data) - 18
    assert _refused(tmp_path, MAGIC + struct.pack("<i", size + 1) + data[18:]) == (
        f"truncated or corrupted IO header at byte 14 (declares {size + 1} bytes, file ends at byte {len(data)})")


def test_a_damaged_io_header_is_named_at_its_own_bytes(tmp_path) -> None:
    """Offsets inside the header count from byte 18, where it starts: a wrong identifier is at
    its byte 4, so byte 22, as is a one-byte header's missing one."""
    header = bytearray(io_header(0, None, INFO))
    header[4:8] = b"IOHX"
    assert _refused(tmp_path, _file(header=bytes(header))).startswith("corrupted IO header at byte 22: ")
    assert _refused(tmp_path, _file(header=b"\x01", packets=[(3, bytes(8))])) == (
        "corrupted IO header at byte 22: file identifier b'' at byte 4, expected b'IOHE'")
    assert _refused(tmp_path, _file(compression=9)) == "the IO header at byte 18 names compression 9; AEDAT 4.0 " \
                                                       "defines 0-4"


@pytest.mark.parametrize("code, name", [(0, "none"), (1, "lz4"), (2, "lz4"), (3, "zstd"), (4, "zstd")])
def test_the_five_compression_codes(code, name) -> None:
    header = inivation.parse_io_header(io_header(code, None, INFO), "f", 18)
    assert header == inivation.IOHeader(name, -1, 3, (260, 346))
    with pytest.raises(dataclasses.FrozenInstanceError):
        header.compression = "none"


# ---- the stream description -------------------------------------------------------------------------------
@pytest.mark.parametrize("info, expected", [
    (_xml(("3", "EVTS", {"sizeX": "1", "sizeY": "1"})), (3, (1, 1))),
    (_xml(("3", "EVTS", {"sizeX": "32768", "sizeY": "2"})), (3, (2, 32768))),
    (_xml(("3", "EVTS", {"sizeX": "640"})), (3, None)),  # half a size: none
    (_xml(("3", "EVTS", {})), (3, None)),
    (_xml(("9", "EVTS", SENSOR), ("4", "EVTS", {}), ("x", "EVTS", {}), ("1", "FRME", {})), (4, None)),
    (INFO + b"\0\0\0", (3, (260, 346))),  # NUL padding after the XML
])
def test_the_lowest_numbered_event_stream_and_its_sensor(info, expected) -> None:
    assert inivation._event_stream(info, "f", 18) == expected


@pytest.mark.parametrize("info, message", [
    (_xml(("3", "EVTS", {"sizeX": "0", "sizeY": "260"})), "event stream 3 states sensor size 0 x 260, expected "
                                                          "positive integers"),
    (_xml(("3", "EVTS", {"sizeX": "346", "sizeY": "-1"})), "event stream 3 states sensor size 346 x -1, expected "
                                                           "positive integers"),
    (_xml(("3", "EVTS", {"sizeX": "32769", "sizeY": "2"})), "event stream 3 states sensor size 32769 x 2, expected "
                                                            "positive integers"),
    (_xml(("3", "EVTS", {"sizeX": "a lot", "sizeY": "2"})), "event stream 3 states sensor size a lot x 2, expected "
                                                            "positive integers"),
    (_xml(("3", "EVTS", {"sizeX": "", "sizeY": "260"})), "event stream 3 states sensor size  x 260, expected "
                                                         "positive integers"),
    (_xml(("7", "IMUS", {})), "no event stream (no 'EVTS' output in the IO header's stream description)"),
    (b"", "the IO header at byte 18 holds no valid stream description (XML: no element found: line 1, column 0)"),
])
def test_a_stream_description_without_a_usable_event_stream_is_one_line(info, message) -> None:
    with pytest.raises(DataError) as caught:
        inivation._event_stream(info, "f", 18)
    assert str(caught.value) == f"f: {message}"


def test_a_header_without_a_description_says_so(tmp_path) -> None:
    assert _refused(tmp_path, _file(header=io_header(0, None, None))) == (
        "the IO header at byte 18 holds no valid stream description (XML: no element found: line 1, column 0)")


# ---- packets ----------------------------------------------------------------------------------------------
def test_event_packets_of_the_event_stream_are_read_in_order_and_others_skipped(tmp_path) -> None:
    later = [(1_700_000_000_000_200, 1, 2, False)]
    data = _file([(3, event_packet(EVENTS)), (7, b"\x01"), (7, bytes(40)), (3, event_packet(later)),
                  (3, event_packet([]))])
    columns, _ = _read(tmp_path, data)
    assert columns["t"].tolist() == [e[0] for e in EVENTS + later]
    assert columns["x"].tolist() == [5, 345, -2, 1] and columns["p"].tolist() == [1, 0, 1, 0]


def test_the_data_table_ends_the_packets_and_may_sit_at_either_edge(tmp_path) -> None:
    """Packets end where the data table starts: right after the header (no packets) or at the
    end of the file (an empty table) are both in range; one byte outside is not."""
    header_len = len(io_header(0, 0, INFO))
    first = 18 + header_len
    columns, _ = _read(tmp_path, _file(table=first) + b"TABLE")
    assert len(columns["t"]) == 0
    packet = (3, event_packet(EVENTS))
    whole = _file([packet], table=first + 8 + len(packet[1]))
    assert _read(tmp_path, whole)[0]["t"].tolist() == [e[0] for e in EVENTS]
    for table in (first - 1, len(whole) + 1):
        assert _refused(tmp_path, _file([packet], table=table)) == (
            f"corrupted IO header at byte 18: its data table position {table} lies outside the packets (bytes "
            f"{first} to {len(_file([packet], table=table))})")


def test_a_packet_walk_that_runs_out_names_the_byte_and_what_it_ran_into(tmp_path) -> None:
    packet = (3, event_packet(EVENTS))
    data = _file([packet])
    pos = len(data)
    assert _refused(tmp_path, data + bytes(5)) == (
        f"truncated or corrupted at byte {pos}: 5 bytes left before the end of the file at byte {pos + 5}, too few "
        "for a packet header")
    assert _refused(tmp_path, data + struct.pack("<ii", 3, 0)) == (
        f"truncated or corrupted at byte {pos}: the packet there (stream 3, 0 bytes) runs past the end of the file "
        f"at byte {pos + 8}")
    assert _refused(tmp_path, data + struct.pack("<ii", -1, 4) + bytes(4)) == (
        f"truncated or corrupted at byte {pos}: the packet there (stream -1, 4 bytes) runs past the end of the file "
        f"at byte {pos + 12}")
    header_len = len(io_header(0, 0, INFO))
    table = 18 + header_len + 8 + len(packet[1]) + 3
    short = _file([packet], table=table)
    assert _refused(tmp_path, short + bytes(8)) == (
        f"truncated or corrupted at byte {table - 3}: 3 bytes left before the data table at byte {table}, too few "
        "for a packet header")


def test_a_damaged_event_packet_is_named_at_its_byte(tmp_path) -> None:
    packet = event_packet(EVENTS)
    pos = len(_file())
    assert _refused(tmp_path, _file([(3, packet + bytes(4))])) == (
        f"corrupted packet at byte {pos}: its FlatBuffer declares {len(packet) - 4} bytes, {len(packet)} decompressed")


# ---- one packet's payload ---------------------------------------------------------------------------------
@pytest.mark.parametrize("buf, message", [
    (b"\x01\0\0", "3 bytes decompressed, too few for a FlatBuffer"),
    (struct.pack("<I", 6) + bytes(4), "its FlatBuffer declares 6 bytes, 4 decompressed"),
])
def test_a_payload_too_short_or_of_the_wrong_size_is_refused(buf, message) -> None:
    with pytest.raises(ValueError) as info:
        inivation.decode_event_packet(buf, "none")
    assert str(info.value) == message


def test_an_empty_flatbuffer_is_refused_where_its_identifier_should_be() -> None:
    """Four bytes of size prefix declaring 0: enough for the prefix, not for a FlatBuffer,
    whose identifier would be at its byte 4, byte 8 of the packet."""
    with pytest.raises(ValueError) as info:
        inivation.decode_event_packet(struct.pack("<I", 0), "none")
    assert str(info.value) == "file identifier b'' at byte 4, expected b'EVTS' (byte 8 of the decompressed packet)"


def test_a_packet_of_another_type_is_refused_at_its_identifier() -> None:
    packet = bytearray(event_packet(EVENTS))
    packet[8:12] = b"IMUS"
    with pytest.raises(ValueError) as info:
        inivation.decode_event_packet(bytes(packet), "none")
    assert str(info.value).endswith("(byte 8 of the decompressed packet)")


def test_a_packet_without_an_event_vector_has_no_events() -> None:
    flatbuffers = pytest.importorskip("flatbuffers")
    builder = flatbuffers.Builder(0)
    builder.StartObject(1)
    builder.FinishSizePrefixed(builder.EndObject(), b"EVTS")
    events = inivation.decode_event_packet(bytes(builder.Output()), "none")
    assert events.dtype == inivation.EVENT_DTYPE and len(events) == 0


def test_the_event_struct_is_the_documented_16_bytes() -> None:
    """int64 timestamp, int16 x, int16 y, bool polarity, 3 bytes of padding."""
    dtype = inivation.EVENT_DTYPE
    assert dtype.itemsize == 16 and [dtype.fields[k][1] for k in ("t", "x", "y", "p")] == [0, 8, 10, 12]


# ---- decompression and its bound --------------------------------------------------------------------------
def _zeros_at_the_bound(zstd, extra: int, sized: bool) -> tuple[bytes, int]:
    """A Zstd frame of zeros that decompresses to exactly the bound + `extra` bytes (the bound:
    1024 times the frame's own length plus 4 KiB); the length moves with the content, so the
    two are iterated to agree."""
    compressor = zstd.ZstdCompressor(write_content_size=sized)
    frame = compressor.compress(bytes(1))
    for _ in range(20):
        size = inivation.MAX_EXPANSION * len(frame) + 4096 + extra
        again = compressor.compress(bytes(size))
        if len(again) == len(frame):
            return again, size
        frame = again
    raise AssertionError("no fixed point")


@pytest.mark.parametrize("sized", [True, False])
def test_a_zstd_frame_may_expand_to_exactly_the_bound_and_not_one_byte_more(sized) -> None:
    zstd = pytest.importorskip("zstandard")
    frame, size = _zeros_at_the_bound(zstd, 0, sized)
    assert len(inivation.decompress(frame, "zstd")) == size
    over, _ = _zeros_at_the_bound(zstd, 1, sized)
    with pytest.raises(ValueError) as info:
        inivation.decompress(over, "zstd")
    assert str(info.value) == ("its Zstd frame claims more than 1024x its size" if sized else
                               "it expands more than 1024x")


def test_an_unsized_frame_over_the_bound_is_caught_across_reads() -> None:
    """Read in steps of 1 MiB: a frame whose output passes the bound only in its second step is
    still refused (the count is the total, not the last step)."""
    zstd = pytest.importorskip("zstandard")
    compressor = zstd.ZstdCompressor(write_content_size=False)
    noise = np.random.default_rng(0).integers(0, 256, 1200, dtype=np.uint8).tobytes()
    content = noise + bytes(1024 * 1300 + 200_000)
    frame = compressor.compress(content)
    bound = inivation.MAX_EXPANSION * len(frame) + 4096
    assert (1 << 20) <= bound < len(content) <= bound + (1 << 20)
    with pytest.raises(ValueError, match="^it expands more than 1024x$"):
        inivation.decompress(frame, "zstd")


@pytest.mark.parametrize("sized", [True, False])
def test_bytes_after_a_zstd_frame_are_counted(sized) -> None:
    """A second frame after the first is counted as bytes that follow, sized or not (the
    streaming reader that bounds an unsized frame stops at the frame's end without a word);
    three stray bytes after an unsized frame are already refused by that reader."""
    zstd = pytest.importorskip("zstandard")
    frame = zstd.ZstdCompressor(write_content_size=sized).compress(event_packet(EVENTS))
    with pytest.raises(ValueError) as info:
        inivation.decompress(frame + b"abc", "zstd")
    assert str(info.value) == ("3 bytes follow the zstd frame" if sized else
                               "the zstd data does not decompress (zstd decompress error: Unknown frame descriptor)")
    more = zstd.ZstdCompressor(write_content_size=sized).compress(b"more")
    with pytest.raises(ValueError) as info:
        inivation.decompress(frame + more, "zstd")
    assert str(info.value) == f"{len(more)} bytes follow the zstd frame"
    assert inivation.decode_event_packet(frame, "zstd")["t"].tolist() == [e[0] for e in EVENTS]


def test_bytes_after_an_lz4_frame_are_counted() -> None:
    lz4 = pytest.importorskip("lz4.frame")
    with pytest.raises(ValueError) as info:
        inivation.decompress(lz4.compress(event_packet(EVENTS)) + b"ab", "lz4")
    assert str(info.value) == "2 bytes follow the lz4 frame"


@pytest.mark.parametrize("compression, module, what", [
    ("lz4", "lz4.frame", "reading an LZ4-compressed AEDAT4 stream"),
    ("zstd", "zstandard", "reading a Zstd-compressed AEDAT4 stream"),
])
def test_a_missing_decompressor_is_one_line_naming_the_extra(monkeypatch, compression, module, what) -> None:
    from e3dpsm.data.formats import CAMERAS_EXTRA

    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(DataError) as info:
        inivation.decompress(b"\x28\xb5\x2f\xfd", compression)
    assert str(info.value) == f"{what} needs the {module!r} package, which is not installed: {CAMERAS_EXTRA}"


def test_an_uncompressed_payload_is_passed_through() -> None:
    payload = memoryview(event_packet(EVENTS))
    assert inivation.decompress(payload, "none") is payload


def test_a_second_unsized_zstd_frame_counts_against_the_bound() -> None:
    """The bounded reader goes on into a frame that follows an unsized one: a second frame of
    8 MB of zeros, far past the payload's bound, is refused by the bound after at most one
    step of 1 MiB past it, not decoded whole."""
    zstd = pytest.importorskip("zstandard")
    first = zstd.ZstdCompressor(write_content_size=False).compress(event_packet(EVENTS))
    second = zstd.ZstdCompressor(write_content_size=False).compress(bytes(8 << 20))
    assert (8 << 20) > inivation.MAX_EXPANSION * len(first + second) + 4096
    with pytest.raises(ValueError) as info:
        inivation.decompress(first + second, "zstd")
    assert str(info.value) == "it expands more than 1024x"


# xxHash32 (github.com/Cyan4973/xxHash, doc/xxhash_spec.md) for inputs under 16 bytes: what an
# LZ4 frame header's checksum byte is made of (the LZ4 frame format, doc/lz4_Frame_format.md:
# the second byte of xxh32 of the descriptor, seed 0). Checked below against lz4's own header.
_P1, _P2, _P3, _P4, _P5 = 2654435761, 2246822519, 3266489917, 668265263, 374761393


def _xxh32_short(data: bytes) -> int:
    def rotl(x: int, r: int) -> int:
        return ((x << r) | (x >> (32 - r))) & 0xFFFFFFFF

    h = (_P5 + len(data)) & 0xFFFFFFFF
    whole = len(data) - len(data) % 4
    for i in range(0, whole, 4):
        h = rotl((h + int.from_bytes(data[i:i + 4], "little") * _P3) & 0xFFFFFFFF, 17) * _P4 & 0xFFFFFFFF
    for byte in data[whole:]:
        h = rotl((h + byte * _P5) & 0xFFFFFFFF, 11) * _P1 & 0xFFFFFFFF
    h = ((h ^ (h >> 15)) * _P2) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * _P3) & 0xFFFFFFFF
    return h ^ (h >> 16)


def _lz4_claiming(lz4, claimed: int) -> bytes:
    """An LZ4 frame of a real packet whose header claims `claimed` bytes of content (header:
    magic, FLG, BD, 8-byte content size, checksum byte), its checksum made to match."""
    frame = bytearray(lz4.compress(event_packet(EVENTS), store_size=True))
    assert frame[14] == (_xxh32_short(bytes(frame[4:14])) >> 8) & 0xFF  # the checksum as lz4 wrote it
    struct.pack_into("<Q", frame, 6, claimed)
    frame[14] = (_xxh32_short(bytes(frame[4:14])) >> 8) & 0xFF
    assert lz4.get_frame_info(bytes(frame))["content_size"] == claimed
    return bytes(frame)


def test_an_lz4_frame_claiming_more_than_the_bound_is_refused_before_decoding() -> None:
    """LZ4 cannot expand past about 255x; a header claiming more is damage, refused on its
    claim. At exactly the bound the claim passes, and the decoder finds the content short."""
    lz4 = pytest.importorskip("lz4.frame")
    length = len(_lz4_claiming(lz4, 1))
    bound = inivation.MAX_EXPANSION * length + 4096
    with pytest.raises(ValueError) as over:
        inivation.decompress(_lz4_claiming(lz4, bound + 1), "lz4")
    assert str(over.value) == "its LZ4 frame claims more than 1024x its size"
    with pytest.raises(ValueError) as at_bound:
        inivation.decompress(_lz4_claiming(lz4, bound), "lz4")
    assert str(at_bound.value).startswith("the lz4 data does not decompress (")
