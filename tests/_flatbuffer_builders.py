"""AEDAT4 FlatBuffers built by Google's own `flatbuffers` Builder (an independent writer,
installed with onnxruntime): an event packet as dv-processing's generated code lays it out and
an IO header with any of its fields left out. Shared by the decoder's tests."""
from __future__ import annotations

import pytest

flatbuffers = pytest.importorskip("flatbuffers")


def event_packet(events: list[tuple[int, int, int, int]]) -> bytes:
    """A size-prefixed EventPacket as dv-processing's generated code builds it (Event: int64
    timestamp, int16 x, int16 y, bool polarity, 3 bytes of padding; 16 bytes, aligned to 8)."""
    builder = flatbuffers.Builder(0)
    builder.StartVector(16, len(events), 8)
    for t, x, y, p in reversed(events):
        builder.Prep(8, 16)
        builder.Pad(3)
        builder.PrependUint8(p)  # a bool is one byte; any value is written as given
        builder.PrependInt16(y)
        builder.PrependInt16(x)
        builder.PrependInt64(t)
    elements = builder.EndVector()
    builder.StartObject(1)
    builder.PrependUOffsetTRelativeSlot(0, elements, 0)
    builder.FinishSizePrefixed(builder.EndObject(), b"EVTS")
    return bytes(builder.Output())


def io_header(compression: int | None, table_position: int | None, info: bytes | None) -> bytes:
    builder = flatbuffers.Builder(0)
    text = builder.CreateString(info) if info is not None else None
    builder.StartObject(3)
    if compression is not None:
        builder.PrependInt32Slot(0, compression, -99)  # -99: never the default, so it is written
    if table_position is not None:
        builder.PrependInt64Slot(1, table_position, -99)
    if text is not None:
        builder.PrependUOffsetTRelativeSlot(2, text, 0)
    builder.Finish(builder.EndObject(), b"IOHE")
    return bytes(builder.Output())


EVENTS = [(1_700_000_000_000_123, 5, 7, True), (1_700_000_000_000_124, 345, 259, False), (-1, -2, 3, True)]
