"""A bounds-checked reader of FlatBuffers tables, for the few AEDAT4 tables e3dpsm reads.

FlatBuffers' own Python runtime trusts its input (no verifier: a damaged offset reads past
the buffer or loops over garbage), so the AEDAT4 decoder reads through these few functions
instead, and every offset and length is checked against the buffer before it is followed.
Nothing here loops over data: reading a field costs a fixed number of steps.

Layout (https://flatbuffers.dev/internals/): a buffer starts with a uint32 offset to its
root table, optionally followed by a 4-byte file identifier. A table starts with an int32
that, subtracted from the table's position, gives its vtable: uint16 vtable size, uint16
table size, then one uint16 per field (its offset inside the table; 0 = absent, the default
applies). A string or vector field holds a uint32 offset, relative to the field, to a
uint32 length followed by the elements.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass


class FlatBufferError(ValueError):
    """A table or field that does not fit its buffer; `offset` is where, within the buffer."""

    def __init__(self, message: str, offset: int) -> None:
        super().__init__(message)
        self.offset = offset


@dataclass(frozen=True)
class Table:
    """A table at `pos` of `buf`, its vtable checked to lie inside the buffer."""

    buf: bytes | memoryview
    pos: int
    field_offsets: tuple[int, ...]  # per field index; 0 = absent
    size: int  # bytes of the table's inline data


def _u32(buf: bytes | memoryview, at: int, what: str) -> int:
    if at < 0 or at + 4 > len(buf):
        raise FlatBufferError(f"{what} at byte {at} lies outside the {len(buf)}-byte buffer", at)
    return struct.unpack_from("<I", buf, at)[0]


def root_table(buf: bytes | memoryview, identifier: bytes | None = None) -> Table:
    """The root table of a buffer (not size-prefixed), checking its 4-byte identifier."""
    if identifier is not None and bytes(buf[4:8]) != identifier:
        raise FlatBufferError(f"file identifier {bytes(buf[4:8])!r} at byte 4, expected {identifier!r}", 4)
    return table_at(buf, _u32(buf, 0, "the root offset"))


def table_at(buf: bytes | memoryview, pos: int) -> Table:
    _u32(buf, pos, "a table")  # bounds check
    vtable = pos - struct.unpack_from("<i", buf, pos)[0]
    if vtable < 0 or vtable + 4 > len(buf):
        raise FlatBufferError(f"the vtable of the table at byte {pos} lies outside the buffer", pos)
    vt_size, size = struct.unpack_from("<HH", buf, vtable)
    if vt_size < 4 or vt_size % 2 or vtable + vt_size > len(buf):
        raise FlatBufferError(f"the vtable at byte {vtable} declares {vt_size} bytes", vtable)
    if size < 4 or pos + size > len(buf):
        raise FlatBufferError(f"the table at byte {pos} declares {size} bytes, past the buffer's end", pos)
    fields = struct.unpack_from(f"<{(vt_size - 4) // 2}H", buf, vtable + 4)
    return Table(buf, pos, fields, size)


def _field(table: Table, index: int, width: int) -> int | None:
    """Where field `index` (of `width` bytes) lies, or None when the table leaves it out."""
    offset = table.field_offsets[index] if index < len(table.field_offsets) else 0
    if offset == 0:
        return None
    if offset < 4 or offset + width > table.size:
        raise FlatBufferError(f"field {index} of the table at byte {table.pos} lies outside the table",
                              table.pos + offset)
    return table.pos + offset


def scalar(table: Table, index: int, fmt: str, default: int) -> int:
    """A scalar field (struct format such as '<i' or '<q'), or its schema default."""
    at = _field(table, index, struct.calcsize(fmt))
    return default if at is None else struct.unpack_from(fmt, table.buf, at)[0]


def vector(table: Table, index: int, element_size: int) -> tuple[int, int] | None:
    """(byte where the elements start, element count) of a vector field, checked to fit."""
    at = _field(table, index, 4)
    if at is None:
        return None
    start = at + _u32(table.buf, at, f"the offset of field {index}")
    count = _u32(table.buf, start, f"the length of field {index}")
    if start + 4 + count * element_size > len(table.buf):
        raise FlatBufferError(f"field {index}'s {count} elements of {element_size} bytes at byte {start + 4} run "
                              f"past the buffer's end at byte {len(table.buf)}", start)
    return start + 4, count


def string(table: Table, index: int) -> bytes | None:
    found = vector(table, index, 1)
    if found is None:
        return None
    start, count = found
    return bytes(table.buf[start:start + count])
