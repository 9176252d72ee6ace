"""Named metadata buffers of a TFLite flatbuffer (the `metadata` table of the TFLite schema:
a name and the index of a buffer holding its bytes), read and written with the schema
module ai-edge-litert ships. Torch-free: the LiteRT runner reads the state layout here."""
from __future__ import annotations

import re
from typing import Any, Callable

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


def rewrite_model(content: bytes, edit: Callable[[Any], None]) -> bytes:
    """The flatbuffer unpacked (schema ModelT), changed by `edit(model)` and packed again.
    Buffers a writer stored past the flatbuffer (offset and size: ai-edge-quantizer does so once
    its weights pass 256 KiB) are moved inside it, where the rewritten table can point at them."""
    import flatbuffers
    import numpy as np

    schema = _schema()
    model = schema.ModelT.InitFromPackedBuf(bytearray(content), 0)
    for buffer in model.buffers or []:
        if buffer.offset > 1:
            buffer.data = np.frombuffer(content, dtype=np.uint8, count=buffer.size, offset=buffer.offset)
            buffer.offset, buffer.size = 0, 0
    edit(model)
    builder = flatbuffers.Builder(len(content) + 1024)
    builder.Finish(model.Pack(builder), file_identifier=TFLITE_IDENTIFIER)
    return bytes(builder.Output())


def with_metadata(content: bytes, name: str, data: bytes) -> bytes:
    """The flatbuffer with metadata entry `name` set to `data` (replaced if present)."""
    import numpy as np

    schema = _schema()

    def edit(model: Any) -> None:
        model.metadata = [m for m in (model.metadata or []) if m.name.decode("utf-8") != name]
        buffer = schema.BufferT()
        buffer.data = np.frombuffer(data, dtype=np.uint8)
        model.buffers.append(buffer)
        entry = schema.MetadataT()
        entry.name = name
        entry.buffer = len(model.buffers) - 1
        model.metadata.append(entry)

    return rewrite_model(content, edit)


def short_tensor_name(subgraph: int, tensor: int) -> str:
    return f"s{subgraph}t{tensor}"


def is_short_tensor_name(name: str) -> bool:
    """Whether `name` is one with_short_tensor_names wrote (not a converter's module path)."""
    return re.fullmatch(r"s\d+t\d+", name) is not None


def with_short_tensor_names(content: bytes) -> bytes:
    """The flatbuffer with every tensor named by its subgraph and index (`s0t12`). litert-torch
    names each tensor by its full module path (about 170 bytes each, 0.25-0.28 MB of `small`'s
    file, a tenth of its INT8 size); no runner reads them: inputs and outputs are bound by the
    signature, whose names stay."""

    def edit(model: Any) -> None:
        for g, graph in enumerate(model.subgraphs or []):
            for t, tensor in enumerate(graph.tensors or []):
                tensor.name = short_tensor_name(g, t)

    return rewrite_model(content, edit)
