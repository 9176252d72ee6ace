"""The bounds-checked FlatBuffers reader (e3dpsm/data/formats/flatbuffer.py) and the AEDAT4
packet decoder, against buffers built by Google's own `flatbuffers` Builder (an independent
writer: installed with onnxruntime), then damaged field by field."""
from __future__ import annotations

import dataclasses
import struct

import numpy as np
import pytest

from e3dpsm.data.formats.flatbuffer import FlatBufferError, Table, root_table, scalar, string, table_at, vector
from e3dpsm.data.formats.inivation import columns, decode_event_packet, parse_io_header
from e3dpsm.errors import DataError

pytest.importorskip("flatbuffers")
from _flatbuffer_builders import EVENTS, event_packet, io_header  # noqa: E402  (needs flatbuffers)

XML = (b'<dv version="2.0"><node name="outInfo" path="/outInfo/">'
       b'<node name="3" path="/outInfo/3/"><attr key="typeIdentifier" type="string">EVTS</attr>'
       b'<node name="info" path="/outInfo/3/info/"><attr key="sizeX" type="int">346</attr>'
       b'<attr key="sizeY" type="int">260</attr></node></node>'
       b'<node name="7" path="/outInfo/7/"><attr key="typeIdentifier" type="string">IMUS</attr></node>'
       b'</node></dv>')


def test_event_packet_built_by_flatbuffers_decodes_to_its_events():
    got = decode_event_packet(event_packet(EVENTS), "none")
    assert got["t"].tolist() == [e[0] for e in EVENTS] and got["x"].tolist() == [e[1] for e in EVENTS]
    assert got["y"].tolist() == [e[2] for e in EVENTS] and got["p"].tolist() == [int(e[3]) for e in EVENTS]
    assert len(decode_event_packet(event_packet([]), "none")) == 0


def test_columns_keep_packet_order_and_read_any_nonzero_polarity_byte_as_on():
    first = decode_event_packet(event_packet(EVENTS), "none")
    second = decode_event_packet(event_packet([(9, 1, 2, 2), (10, 3, 4, 255)]), "none")
    got = columns([first, second])
    assert got["t"].tolist() == [e[0] for e in EVENTS] + [9, 10] and got["x"].tolist() == [5, 345, -2, 1, 3]
    assert got["p"].tolist() == [1, 0, 1, 1, 1] and got["p"].dtype == np.uint8 and got["x"].dtype == np.int32


def test_io_header_fields_and_their_defaults():
    header = parse_io_header(io_header(3, 1234, XML), "h", 18)
    assert (header.compression, header.data_table_position) == ("zstd", 1234)
    assert header.event_stream == 3 and header.sensor_hw == (260, 346)  # EVTS, not the IMU stream
    header = parse_io_header(io_header(None, None, XML), "h", 18)  # absent fields: the schema's defaults
    assert (header.compression, header.data_table_position) == ("none", -1)


def test_io_header_without_an_event_stream_or_with_bad_xml_is_refused():
    with pytest.raises(DataError, match="h: no event stream"):
        parse_io_header(io_header(1, -1, XML.replace(b"EVTS", b"FRME")), "h", 18)
    with pytest.raises(DataError, match=r"h: the IO header at byte 18 holds no valid stream description"):
        parse_io_header(io_header(1, -1, XML[:-3]), "h", 18)
    with pytest.raises(DataError, match="names compression 9"):
        parse_io_header(io_header(9, -1, XML), "h", 18)
    with pytest.raises(DataError, match="h: no event stream"):  # a stream id no int() takes (> 4300 digits)
        parse_io_header(io_header(1, -1, XML.replace(b'name="3"', b'name="' + b"9" * 5000 + b'"')), "h", 18)


def _table_pos(buf: bytes) -> int:
    return struct.unpack_from("<I", buf, 0)[0]


@pytest.mark.parametrize("damage, message", [
    (lambda b: struct.pack_into("<I", b, 0, len(b) + 100), r"a table at byte \d+ lies outside"),
    (lambda b: struct.pack_into("<i", b, _table_pos(b), -(len(b) * 2)), r"the vtable of the table .* outside"),
    (lambda b: struct.pack_into("<I", b, 4, 0x7FFFFFF0), r"identifier"),
])
def test_damaged_offsets_are_refused_with_their_byte(damage, message):
    buf = bytearray(io_header(1, 10, XML))
    damage(buf)
    with pytest.raises(FlatBufferError, match=message):
        table = root_table(bytes(buf), b"IOHE")
        string(table, 2)


def test_a_vector_longer_than_its_buffer_is_refused_before_it_is_read():
    buf = bytearray(event_packet(EVENTS))[4:]  # without the size prefix
    table = root_table(bytes(buf), b"EVTS")
    start, count = vector(table, 0, 16)
    assert count == 3
    struct.pack_into("<I", buf, start - 4, 4)  # four elements claimed, three present
    with pytest.raises(FlatBufferError, match=r"field 0's 4 elements of 16 bytes at byte \d+ run past"):
        vector(root_table(bytes(buf), b"EVTS"), 0, 16)
    struct.pack_into("<I", buf, start - 4, 0xFFFFFFFF)  # a count whose byte size overflows 32 bits
    with pytest.raises(FlatBufferError, match="run past"):
        vector(root_table(bytes(buf), b"EVTS"), 0, 16)


def test_a_field_outside_its_table_is_refused():
    buf = bytearray(io_header(2, 77, XML))
    table = root_table(bytes(buf), b"IOHE")
    assert scalar(table, 1, "<q", -1) == 77
    vtable = table.pos - struct.unpack_from("<i", buf, table.pos)[0]
    struct.pack_into("<H", buf, vtable + 2, 6)  # the table now claims 6 bytes: field 1 lies beyond
    with pytest.raises(FlatBufferError, match="field 1 of the table at byte .* lies outside the table"):
        scalar(root_table(bytes(buf), b"IOHE"), 1, "<q", -1)


def test_packet_size_prefix_must_match_what_was_decompressed():
    packet = event_packet(EVENTS)
    with pytest.raises(ValueError, match=r"declares \d+ bytes, \d+ decompressed"):
        decode_event_packet(packet + b"\0\0\0\0", "none")
    with pytest.raises(ValueError, match="too few for a FlatBuffer"):
        decode_event_packet(b"\1\0", "none")
    np.testing.assert_array_equal(decode_event_packet(packet, "none")["x"], [5, 345, -2])


def test_a_packet_that_would_expand_past_the_bound_is_refused():
    lz4 = pytest.importorskip("lz4.frame")
    zstd = pytest.importorskip("zstandard")
    huge = bytes(20_000_000)  # Zstd compresses it > 1024x (LZ4 cannot exceed ~255x)
    packet = zstd.ZstdCompressor().compress(huge)
    assert len(huge) > 1024 * len(packet) + 4096
    with pytest.raises(ValueError, match="its Zstd frame claims more than 1024x its size"):
        decode_event_packet(packet, "zstd")
    unsized = zstd.ZstdCompressor(write_content_size=False).compress(huge)  # found while reading
    with pytest.raises(ValueError, match="it expands more than 1024x"):
        decode_event_packet(unsized, "zstd")
    with pytest.raises(ValueError, match=r"the lz4 data does not decompress \(Frame incomplete"):
        decode_event_packet(lz4.compress(event_packet(EVENTS))[:-6], "lz4")
    with pytest.raises(ValueError, match="3 bytes follow the lz4 frame"):
        decode_event_packet(lz4.compress(event_packet(EVENTS)) + b"abc", "lz4")
    with pytest.raises(ValueError, match="3 bytes follow the zstd frame"):
        decode_event_packet(zstd.ZstdCompressor().compress(event_packet(EVENTS)) + b"abc", "zstd")
    unsized = zstd.ZstdCompressor(write_content_size=False).compress(event_packet(EVENTS))
    np.testing.assert_array_equal(decode_event_packet(unsized, "zstd")["t"], [e[0] for e in EVENTS])


# Buffers laid out byte by byte after https://flatbuffers.dev/internals/ (the module doc): each
# boundary is met exactly, then missed by one byte.

def hand_laid(*, field0: int = 4, field1: int = 8, table_size: int = 12, to_string: int = 4,
              tail: bytes = b"") -> bytes:
    """Bytes 0-3: the root offset (16); 4-7: the identifier "TEST"; 8-15: the vtable (8 bytes,
    a 12-byte table, field 0 at +4, field 1 at +8); 16-27: the table (int32 8 back to its vtable,
    int32 -7, uint32 4: the string lies 4 bytes after this field, at 28); 28-36: the string
    (length 5, "hello"). The buffer ends where the string does."""
    return (struct.pack("<I", 16) + b"TEST" + struct.pack("<HHHH", 8, table_size, field0, field1)
            + struct.pack("<iiI", 8, -7, to_string) + struct.pack("<I", 5) + b"hello" + tail)


def test_a_hand_laid_table_reads_every_field_up_to_the_buffers_last_byte():
    """The table at byte 16, its two fields (-7; "hello", whose last byte is the buffer's), a
    field past the vtable or marked absent read as the default, from bytes or a memoryview."""
    buf = hand_laid()
    assert len(buf) == 37
    for source in (buf, memoryview(buf)):
        table = root_table(source, b"TEST")
        assert (table.pos, table.field_offsets, table.size) == (16, (4, 8), 12)
        assert scalar(table, 0, "<i", 99) == -7 and scalar(table, 1, "<I", 0) == 4
        assert string(table, 1) == b"hello" and vector(table, 1, 1) == (32, 5)
        # a field past the end of the vtable, or one the vtable marks absent (0): the default
        assert scalar(table, 2, "<i", 99) == 99 and string(table, 2) is None and vector(table, 3, 4) is None
    assert root_table(buf).pos == 16  # no identifier asked: none checked
    assert scalar(root_table(hand_laid(field0=0)), 0, "<i", 99) == 99
    with pytest.raises(dataclasses.FrozenInstanceError):  # a table stays the one whose vtable was checked
        root_table(buf).pos = 0


@pytest.mark.parametrize("buf", [b"", b"\x10\0\0"])
def test_a_buffer_shorter_than_its_root_offset_is_refused(buf):
    """Under 4 bytes there is no root offset to read: said so, at byte 0."""
    with pytest.raises(FlatBufferError, match=rf"^the root offset at byte 0 lies outside the {len(buf)}-byte buffer$"):
        root_table(buf)


def test_a_string_whose_length_lies_past_the_buffer_is_refused_there():
    """Field 1 (at byte 24) points 100 bytes on: its length would be read at byte 124 of 37."""
    with pytest.raises(FlatBufferError, match=r"^the length of field 1 at byte 124 lies outside the 37-byte buffer$"):
        string(root_table(hand_laid(to_string=100)), 1)


def test_a_wrong_identifier_is_refused_at_byte_4():
    """Bytes 4-7 are not the identifier asked for: both named, at byte 4."""
    with pytest.raises(FlatBufferError, match=r"^file identifier b'TEST' at byte 4, expected b'EVTS'$") as refused:
        root_table(hand_laid(), b"EVTS")
    assert refused.value.offset == 4


def test_a_string_one_byte_short_is_refused_where_its_length_is():
    """The buffer cut one byte before the string's end: refused at its length (byte 28); and a
    vector's byte size is its count times its element size (5 x 2 bytes: 9 refused, 10 read)."""
    with pytest.raises(FlatBufferError, match=r"^field 1's 5 elements of 1 bytes at byte 32 run past the "
                                              r"buffer's end at byte 36$") as refused:
        string(root_table(hand_laid()[:-1]), 1)
    assert refused.value.offset == 28
    with pytest.raises(FlatBufferError, match="run past"):
        vector(root_table(hand_laid(tail=b"\0" * 4)), 1, 2)  # 10 bytes wanted, 9 there
    assert vector(root_table(hand_laid(tail=b"\0" * 5)), 1, 2) == (32, 5)  # exactly 10


@pytest.mark.parametrize("offset, fits", [(8, True), (9, False), (3, False), (2, False)])
def test_a_field_must_lie_inside_its_table_after_the_vtable_offset(offset, fits):
    """Field 1 (4 bytes) at +8 ends at the 12-byte table's end; at +9 it would not; below +4 it
    would overlap the table's own offset to its vtable."""
    table = root_table(hand_laid(field1=offset))
    if fits:
        assert scalar(table, 1, "<I", 0) == 4
        return
    with pytest.raises(FlatBufferError, match=r"^field 1 of the table at byte 16 lies outside the table$") as refused:
        scalar(table, 1, "<I", 0)
    assert refused.value.offset == 16 + offset


def table_then_vtable(vt_size: int = 4, size: int = 4, extra: bytes = b"") -> bytes:
    """A table at byte 0 (4 bytes: its offset to its vtable, -4, so the vtable follows it), then
    the vtable (a `vt_size`-byte vtable of a `size`-byte table, no fields), then `extra`."""
    return struct.pack("<i", -4) + struct.pack("<HH", vt_size, size) + extra


def test_a_table_and_its_vtable_may_reach_the_buffers_last_byte():
    """Each bound is inclusive: a vtable ending at the buffer's end, one at byte 0, a table's
    offset in the last 4 bytes, a table as long as the buffer."""
    assert table_at(table_then_vtable(), 0) == Table(table_then_vtable(), 0, (), 4)
    vtable_then_table = struct.pack("<HH", 4, 4) + struct.pack("<i", 4)  # vtable at byte 0, table at 4
    assert table_at(vtable_then_table, 4).size == 4
    assert table_at(table_then_vtable(size=8), 0).size == 8  # the table's last byte is the buffer's


@pytest.mark.parametrize("buf, pos, message, offset", [
    (table_then_vtable()[:-1], 0, r"^the vtable of the table at byte 0 lies outside the buffer$", 0),
    (struct.pack("<i", 8), 0, r"^the vtable of the table at byte 0 lies outside the buffer$", 0),
    (table_then_vtable(vt_size=2), 0, r"^the vtable at byte 4 declares 2 bytes$", 4),
    (table_then_vtable(vt_size=5, extra=b"\0"), 0, r"^the vtable at byte 4 declares 5 bytes$", 4),
    (table_then_vtable(vt_size=6), 0, r"^the vtable at byte 4 declares 6 bytes$", 4),
    (table_then_vtable(size=2), 0, r"^the table at byte 0 declares 2 bytes, past the buffer's end$", 0),
    (table_then_vtable(size=9), 0, r"^the table at byte 0 declares 9 bytes, past the buffer's end$", 0),
    (table_then_vtable(), -4, r"^a table at byte -4 lies outside the 8-byte buffer$", -4),
    (table_then_vtable(), 5, r"^a table at byte 5 lies outside the 8-byte buffer$", 5),
])
def test_a_table_or_vtable_that_does_not_fit_is_refused_with_its_byte(buf, pos, message, offset):
    """A vtable before byte 0 (8 back from byte 0) or past the end, one of under 4 bytes, of an
    odd size or longer than the buffer; a table longer than the buffer or under 4 bytes; a
    table offset before the buffer (struct would read it from the end) or too near its end."""
    with pytest.raises(FlatBufferError, match=message) as refused:
        table_at(buf, pos)
    assert refused.value.offset == offset
