"""Named metadata buffers of a TFLite flatbuffer (the `metadata` table of the TFLite schema:
a name and the index of a buffer holding its bytes), read and written with the schema
module ai-edge-litert ships. Torch-free: the LiteRT runner reads the state layout here."""
from __future__ import annotations

TFLITE_IDENTIFIER = b"TFL3"


def _schema():
    from ai_edge_litert import schema_py_generated

    return schema_py_generated


def read_metadata(content: bytes) -> dict[str, bytes]:
    """Every metadata entry of a .tflite file's bytes, by name. A buffer stored past the
    flatbuffer (offset and size, as large models do) is read from there."""
    schema = _schema()
    if content[4:8] != TFLITE_IDENTIFIER:
        raise ValueError("not a TFLite flatbuffer (no TFL3 identifier)")
    model = schema.Model.GetRootAs(content, 0)
    entries: dict[str, bytes] = {}
    for i in range(model.MetadataLength()):
        entry = model.Metadata(i)
        buffer = model.Buffers(entry.Buffer())
        if buffer.Offset() > 1:
            data = content[buffer.Offset(): buffer.Offset() + buffer.Size()]
        else:
            data = buffer.DataAsNumpy().tobytes() if buffer.DataLength() else b""
        entries[entry.Name().decode("utf-8")] = data
    return entries


def with_metadata(content: bytes, name: str, data: bytes) -> bytes:
    """The flatbuffer with metadata entry `name` set to `data` (replaced if present). Buffers a
    writer stored past the flatbuffer (offset and size: ai-edge-quantizer does so once its
    weights pass 256 KiB) are moved inside it, where the rewritten table can point at them."""
    import flatbuffers
    import numpy as np

    schema = _schema()
    model = schema.ModelT.InitFromPackedBuf(bytearray(content), 0)
    for buffer in model.buffers or []:
        if buffer.offset > 1:
            buffer.data = np.frombuffer(content, dtype=np.uint8, count=buffer.size, offset=buffer.offset)
            buffer.offset, buffer.size = 0, 0
    model.metadata = [m for m in (model.metadata or []) if m.name.decode("utf-8") != name]
    buffer = schema.BufferT()
    buffer.data = np.frombuffer(data, dtype=np.uint8)
    model.buffers.append(buffer)
    entry = schema.MetadataT()
    entry.name = name
    entry.buffer = len(model.buffers) - 1
    model.metadata.append(entry)
    builder = flatbuffers.Builder(len(content) + len(data) + 1024)
    builder.Finish(model.Pack(builder), file_identifier=TFLITE_IDENTIFIER)
    return bytes(builder.Output())
