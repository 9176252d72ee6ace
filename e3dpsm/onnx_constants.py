"""Folded constants that repeat a small block, stored as the block and a `Tile`.

Constant folding (the exporter's and onnxsim's, ONNX Runtime's pre-pass before quantising)
turns parameter-only subgraphs into one initializer. Where the subgraph tiled a small
tensor, the initializer stores every repeat. The deformable attention's sampling origin is
one: its reference points laid out once per (head, point) slot (`layers/deformable.py`,
`(2 * reference - 1).repeat(1, slots)`), an [H*W, 2 * slots] float32 tensor whose columns
repeat with period 2. On the committed `small` at 96 x 128 the two attention levels' origins
are 61 KB of the fp32 graph, and 61 KB of its INT8 graph, where they are the largest float
tensors left; at the pipeline's resolution, 276 KB.

`retile_constants` stores such an initializer as its smallest repeating block and a `Tile`
node whose output keeps the initializer's name: the graph computes the same tensor, bit for
bit. ONNX Runtime and OpenVINO fold the Tile again when they load the graph, so it costs
nothing per step. Only float initializers read by elementwise arithmetic are touched: a
weight read by Conv/MatMul/Gemm, a Q/DQ input or a shape stays an initializer, as the
quantisers, weight prepacking and shape inference expect.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import onnx
from onnx import numpy_helper

# Readers a Tile output may feed: elementwise arithmetic computes the same from either.
ELEMENTWISE_READERS = frozenset({"Add", "Sub", "Mul", "Div"})
# The types ONNX Runtime's CPU Tile kernel takes (1.31: no float16 or bfloat16): a Tile it
# cannot run is neither folded on load nor run without casts around it.
FLOAT_TYPES = frozenset({onnx.TensorProto.FLOAT, onnx.TensorProto.DOUBLE})
MIN_BYTES_SAVED = 1024  # below this, the two extra initializers and a node are not worth it


@dataclass(frozen=True)
class Retiled:
    constants: int  # initializers stored as a block and a Tile
    bytes_saved: int  # of the serialised graph

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


def repeating_block(array: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]]:
    """(block, repeats) with np.tile(block, repeats) equal to `array` byte for byte, the block
    the smallest such along each axis in turn (the shortest period dividing each axis's
    length); (array, ones) where nothing repeats."""
    block = np.asarray(array)
    repeats = [1] * block.ndim
    for axis in range(block.ndim):
        length = block.shape[axis]
        for period in _divisors(length)[:-1]:
            candidate = np.take(block, np.arange(period), axis=axis)
            reps = [1] * block.ndim
            reps[axis] = length // period
            if np.tile(candidate, reps).tobytes() == block.tobytes():
                block, repeats[axis] = candidate, length // period
                break
    return np.ascontiguousarray(block), tuple(repeats)


def _divisors(n: int) -> list[int]:
    small = [d for d in range(1, int(n ** 0.5) + 1) if n % d == 0]
    return sorted({*small, *(n // d for d in small)})


def retile_constants(model: onnx.ModelProto, min_bytes_saved: int = MIN_BYTES_SAVED) -> Retiled:
    """Store, in place, each float initializer that only elementwise arithmetic reads and
    that repeats a block saving at least `min_bytes_saved` bytes, as `<name>::block`,
    `<name>::repeats` and a Tile node `<name>::tile` whose output is `<name>` (module
    docstring). Graphs with subgraphs are left alone (their readers are not all visible)."""
    graph = model.graph
    if any(attr.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
           for node in graph.node for attr in node.attribute):
        return Retiled(0, 0)
    readers: dict[str, set[str]] = {}
    for node in graph.node:
        for name in node.input:
            readers.setdefault(name, set()).add(node.op_type)
    protected = {v.name for v in (*graph.input, *graph.output)}
    tiles: list[onnx.NodeProto] = []
    size = model.ByteSize()
    for index, init in enumerate(list(graph.initializer)):
        ops = readers.get(init.name)
        if init.data_type not in FLOAT_TYPES or not ops or not ops <= ELEMENTWISE_READERS or init.name in protected:
            continue
        array = numpy_helper.to_array(init)
        block, repeats = repeating_block(array)
        gain = array.nbytes - block.nbytes - 8 * len(repeats)
        if gain < min_bytes_saved:
            continue
        name = init.name  # `init` is the entry rewritten below
        block_name, repeats_name = f"{name}::block", f"{name}::repeats"
        graph.initializer[index].CopyFrom(numpy_helper.from_array(block.astype(array.dtype), block_name))
        graph.initializer.append(numpy_helper.from_array(np.asarray(repeats, np.int64), repeats_name))
        tiles.append(onnx.helper.make_node("Tile", [block_name, repeats_name], [name], name=f"{name}::tile"))
    # Ahead of every reader: initializers are available from the start.
    for offset, node in enumerate(tiles):
        graph.node.insert(offset, node)
    return Retiled(len(tiles), size - model.ByteSize())
