"""Short names for what the quantiser adds, and no stored shapes: a smaller QDQ artifact.

ONNX Runtime's quantiser names every tensor and node it adds after the float tensor it
stands for (`<x>_QuantizeLinear_Output`, `<w>_quantized`, `<w>_scale`, `<w>_zero_point`,
`<x>_DequantizeLinear`, ...), and keeps the shapes inferred before quantising (value_info).
It also writes one initializer per use where many are equal (all-zero zero points, equal
int32 biases): 11% of `small`'s full-integer file, for nothing a runtime reads. What stays: every name the
float graph had (diagnose matches tensors by them and reads a quantised tensor behind its
Q/DQ pair by structure; the search and the report name float graph nodes), the graph's
inputs and outputs, and the metadata. Runtimes infer shapes themselves, as
`onnx.shape_inference` does for the tools that need types (e3dpsm.onnx_groups).

The short names are `q<n>` (a QuantizeLinear and its output), `dq<n>` (a DequantizeLinear
and its output) and `q<n>.s` / `.z` / `.w` (scale, zero point, the integer weight or bias
it reads), numbered in graph order.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Iterable

import onnx
import onnx.numpy_helper

_PREFIX = {"QuantizeLinear": "q", "DequantizeLinear": "dq"}
_INPUT_SUFFIX = (".w", ".s", ".z")  # QuantizeLinear / DequantizeLinear inputs: x, scale, zero point


@dataclass(frozen=True)
class Compaction:
    renamed: int  # names changed (tensors and nodes)
    value_info_dropped: int
    initializers_shared: int  # initializers dropped for an equal one (same type, shape, bytes)
    bytes_saved: int

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


def compact_qdq(model: onnx.ModelProto, keep: Iterable[str] = ()) -> Compaction:
    """Rename, in place, the Q/DQ nodes and the tensors only they introduced, share equal
    initializers the quantiser added, drop value_info.

    `keep`: names that must not change besides the graph's inputs and outputs (the float
    graph's tensor and node names). Graphs with subgraphs (If, Loop) are only stripped of
    value_info: a rename would have to follow names into them."""
    before = model.ByteSize()
    graph = model.graph
    dropped = len(graph.value_info)
    del graph.value_info[:]
    if any(attr.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
           for node in graph.node for attr in node.attribute):
        return Compaction(0, dropped, 0, before - model.ByteSize())

    protected = {*keep, *(v.name for v in graph.input), *(v.name for v in graph.output)}
    shared = _share_equal_initializers(graph, protected)
    initializers = {init.name for init in graph.initializer}
    # Node names and tensor names are separate namespaces in ONNX.
    taken_nodes = protected | {n.name for n in graph.node}
    taken_tensors = protected | initializers | {t for n in graph.node for t in (*n.input, *n.output)}
    rename: dict[str, str] = {}
    node_names: dict[int, str] = {}
    counters = {prefix: 0 for prefix in _PREFIX.values()}

    def fresh(base: str, taken: set[str]) -> str:
        name = base
        while name in taken:
            name += "_"
        taken.add(name)
        return name

    for index, node in enumerate(graph.node):
        prefix = _PREFIX.get(node.op_type)
        if prefix is None:
            continue
        stem = f"{prefix}{counters[prefix]}"
        counters[prefix] += 1
        if node.name not in protected:
            node_names[index] = fresh(stem, taken_nodes)
        out = node.output[0]
        if out not in protected and out not in rename:
            rename[out] = fresh(stem, taken_tensors)
        for position, tensor in enumerate(node.input):
            if tensor in initializers and tensor not in protected and tensor not in rename:
                rename[tensor] = fresh(stem + _INPUT_SUFFIX[position], taken_tensors)

    for index, node in enumerate(graph.node):
        if index in node_names:
            node.name = node_names[index]
        for position, tensor in enumerate(node.input):
            if tensor in rename:
                node.input[position] = rename[tensor]
        for position, tensor in enumerate(node.output):
            if tensor in rename:
                node.output[position] = rename[tensor]
    for init in graph.initializer:
        if init.name in rename:
            init.name = rename[init.name]
    return Compaction(len(rename) + len(node_names), dropped, shared, before - model.ByteSize())


def _share_equal_initializers(graph: onnx.GraphProto, protected: set[str]) -> int:
    """Point readers of an unprotected initializer at the first equal one; drop it. Returns
    how many were dropped. Equal: same element type, shape and bytes (ORT does the same at
    load, its constant sharing; here the file carries one copy)."""
    first: dict[tuple, str] = {}
    alias: dict[str, str] = {}
    ordered = sorted(graph.initializer, key=lambda init: init.name not in protected)  # protected names lead
    for init in ordered:
        key = (init.data_type, tuple(init.dims), onnx.numpy_helper.to_array(init).tobytes())
        if key in first and init.name not in protected:
            alias[init.name] = first[key]
        else:
            first.setdefault(key, init.name)
    if not alias:
        return 0
    for node in graph.node:
        for position, tensor in enumerate(node.input):
            if tensor in alias:
                node.input[position] = alias[tensor]
    kept = [init for init in graph.initializer if init.name not in alias]
    del graph.initializer[:]
    graph.initializer.extend(kept)
    return len(alias)


def graph_names(model: onnx.ModelProto) -> set[str]:
    """Every node, tensor and initializer name of `model` (what `compact_qdq` keeps)."""
    graph = model.graph
    return ({n.name for n in graph.node} | {t for n in graph.node for t in (*n.input, *n.output)}
            | {i.name for i in graph.initializer} | {v.name for v in (*graph.input, *graph.output)})
