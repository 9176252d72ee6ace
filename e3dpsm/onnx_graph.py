"""Producer / consumer index of an ONNX graph, shared by the graph walkers of the profiler
(which module a node belongs to) and the quantiser (which nodes carry state)."""
from __future__ import annotations

import os
from collections import defaultdict
from pathlib import Path
from typing import Callable, Iterable

import onnx

from e3dpsm.errors import DataError


def read_onnx(path: str | os.PathLike, load_external_data: bool = True) -> onnx.ModelProto:
    """The ONNX model at `path`; DataError, one line, when it is missing or does not parse."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"model {path} does not exist")
    try:
        return onnx.load(str(path), load_external_data=load_external_data)
    except Exception as exc:  # onnx raises DecodeError and friends on damaged files
        first = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise DataError(f"{path} is not a readable ONNX file: {first[:300]}") from exc


def with_outputs(model: onnx.ModelProto, names: Iterable[str]) -> onnx.ModelProto:
    """A copy of `model` that also outputs the named intermediate tensors (calibration
    histograms, diagnosis), each once; shapes and types are left for the runtime to infer."""
    exposed = onnx.ModelProto()
    exposed.CopyFrom(model)
    present = {o.name for o in exposed.graph.output}
    for name in names:
        if name not in present:
            exposed.graph.output.append(onnx.ValueInfoProto(name=name))
            present.add(name)
    return exposed


def drop_unused_initializers(model: onnx.ModelProto, among: Iterable[str] | None = None) -> None:
    """Remove, in place, the initializers no node reads (subgraphs included); only those named
    in `among` when given (a pass that removed nodes drops what they alone read)."""
    used = {i for n in model.graph.node for i in n.input}
    used |= {i for n in model.graph.node for a in n.attribute if a.type == onnx.AttributeProto.GRAPH
             for sub in a.g.node for i in sub.input}
    droppable = {i.name for i in model.graph.initializer} if among is None else set(among)
    keep = [i for i in model.graph.initializer if i.name in used or i.name not in droppable]
    del model.graph.initializer[:]
    model.graph.initializer.extend(keep)


def restore_interface_types(model: onnx.ModelProto, source: onnx.ModelProto) -> None:
    """Give `model`'s graph inputs and outputs, in place, the types `source` declares for the
    same names (shapes with their axis names: the export's "batch"), where a pass that
    re-infers shapes (ONNX Runtime's symbolic shape inference, quantize's pre-pass) renamed
    the axes; the interface is the export's contract (export/spec.py). Shapes inside are
    left as inferred."""
    declared = {v.name: v.type for v in (*source.graph.input, *source.graph.output)}
    for value in (*model.graph.input, *model.graph.output):
        if value.name in declared:
            value.type.CopyFrom(declared[value.name])


def node_key(node: onnx.NodeProto) -> str:
    """A node's name, or its first output's name if it has none (outputs are unique)."""
    return node.name or node.output[0]


class GraphIndex:
    """Nodes by key (`node_key`), in graph order, with who produces and who consumes each tensor."""

    def __init__(self, model: onnx.ModelProto) -> None:
        self.nodes: dict[str, onnx.NodeProto] = {node_key(n): n for n in model.graph.node}
        if len(self.nodes) != len(model.graph.node):
            raise ValueError("graph has duplicate node names; re-export it")
        self.producer: dict[str, str] = {}
        self.consumers: dict[str, list[str]] = defaultdict(list)
        for key, node in self.nodes.items():
            for out in node.output:
                self.producer[out] = key
            for inp in node.input:
                if inp:
                    self.consumers[inp].append(key)

    def producers_of(self, key: str, follow: Callable[[str], bool] = lambda tensor: True) -> list[str]:
        """Nodes producing `key`'s inputs, through the tensors `follow` accepts."""
        return [self.producer[t] for t in self.nodes[key].input if t in self.producer and follow(t)]

    def consumers_of(self, key: str, follow: Callable[[str], bool] = lambda tensor: True) -> list[str]:
        """Nodes consuming `key`'s outputs, through the tensors `follow` accepts."""
        return [c for t in self.nodes[key].output if follow(t) for c in self.consumers.get(t, ())]

    def descendants(self, tensors: Iterable[str]) -> set[str]:
        """Nodes reachable from the given tensors."""
        return self._closure([c for t in tensors for c in self.consumers.get(t, [])], self.consumers_of)

    def ancestors(self, tensors: Iterable[str]) -> set[str]:
        """Nodes the given tensors depend on."""
        return self._closure([self.producer[t] for t in tensors if t in self.producer], self.producers_of)

    @staticmethod
    def _closure(start: list[str], neighbours: Callable[[str], list[str]]) -> set[str]:
        seen: set[str] = set()
        stack = list(start)
        while stack:
            key = stack.pop()
            if key not in seen:
                seen.add(key)
                stack.extend(neighbours(key))
        return seen
