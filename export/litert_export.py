"""`e3dpsm convert litert`: the step graph as a LiteRT model (`step.tflite`) through
litert-torch, run by ai-edge-litert's interpreter (XNNPACK delegate on CPU). The signature
keeps the ONNX graph's input and output names (export/edge_export.NamedStepGraph); the state
layout travels in the metadata buffer `e3dpsm` (runtime/tflite_metadata.py)."""
from __future__ import annotations

import os
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from e3dpsm.export.edge_export import NamedStepGraph, artifact_contract, export_ready
from e3dpsm.models import E3DPSM
from e3dpsm.runtime.artifact_metadata import EMBEDDED_NAME, encode
from e3dpsm.utils.extras import require
from e3dpsm.utils.io import atomic_path

FORMAT = "litert"
# The TFLite builtins that carry the step's multiply-accumulates (op coverage in convert.json).
MAC_OPS = ("CONV_2D", "DEPTHWISE_CONV_2D", "FULLY_CONNECTED", "BATCH_MATMUL")


@dataclass(frozen=True)
class LiteRTOptions:
    attention_form: str = "gather"
    keep_tensor_names: bool = False  # litert-torch's module-path names; short ones otherwise (write_litert)


@dataclass
class LiteRTResult:
    path: str
    bytes: int
    seconds: dict[str, float]
    ops: dict[str, Any]
    options: dict[str, Any]
    artifact: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dict(vars(self))


def tflite_op_histogram(content: bytes) -> dict[str, int]:
    """Operator count by builtin name (custom ops by their name) of subgraph 0."""
    from ai_edge_litert import schema_py_generated as schema

    names = {v: k for k, v in vars(schema.BuiltinOperator).items() if not k.startswith("_")}
    model = schema.Model.GetRootAs(content, 0)
    codes = [model.OperatorCodes(i) for i in range(model.OperatorCodesLength())]
    graph = model.Subgraphs(0)
    counts: Counter[str] = Counter()
    for i in range(graph.OperatorsLength()):
        code = codes[graph.Operators(i).OpcodeIndex()]
        builtin = max(code.BuiltinCode(), code.DeprecatedBuiltinCode())
        name = names.get(builtin, str(builtin))
        counts[code.CustomCode().decode() if name == "CUSTOM" else name] += 1
    return dict(counts.most_common())


def delegate_partitions(content: bytes, threads: int = 1) -> int:
    """How many partitions the interpreter's default XNNPACK delegate cut the graph into (each
    boundary is a hand-over to TFLite's own kernels). ai-edge-litert's Python API lists the
    delegate nodes beside the nodes they replaced, not the execution plan, so which operators
    stay outside is not read here (docs/edge.md)."""
    from ai_edge_litert.interpreter import Interpreter

    interpreter = Interpreter(model_content=content, num_threads=threads)
    interpreter.allocate_tensors()
    nodes = interpreter._get_ops_details()  # experimental API: a report figure only
    return sum(1 for d in nodes if d["op_name"] == "DELEGATE")


def litert_content(model: E3DPSM, options: LiteRTOptions = LiteRTOptions()) -> bytes:
    """The step as a .tflite flatbuffer (no state layout yet: write_litert adds it)."""
    litert_torch = require("litert_torch", "to write .tflite models")
    require("ai_edge_litert", "to write .tflite models")
    wrapper = NamedStepGraph(model).eval()  # the wrapper has no layers of its own; eval() says so to the converter
    with export_ready(model, options.attention_form):
        converted = litert_torch.convert(wrapper, sample_kwargs=wrapper.example_kwargs())
    return converted.model_content()


def embed_contract(content: bytes, model: E3DPSM, options: LiteRTOptions, precision: str,
                   extra_record: dict[str, Any] | None = None) -> tuple[bytes, dict[str, Any]]:
    """(`content` with the state layout and the artifact record in its `e3dpsm` metadata, the record)."""
    from e3dpsm.runtime.tflite_metadata import with_metadata

    meta, record = artifact_contract(model, FORMAT, precision, options.attention_form,
                                     ("litert-torch", "ai-edge-litert"), extra_record)
    return with_metadata(content, EMBEDDED_NAME, encode(meta, record).encode("utf-8")), record


def write_litert(content: bytes, model: E3DPSM, path: str | os.PathLike, options: LiteRTOptions, precision: str,
                 seconds: dict[str, float], extra_record: dict[str, Any] | None = None) -> LiteRTResult:
    """Write `content` to `path` (atomically) with the state layout inside; sizes, timings, ops."""
    started = time.perf_counter()
    if not options.keep_tensor_names:
        from e3dpsm.runtime.tflite_metadata import with_short_tensor_names

        content = with_short_tensor_names(content)
    content, record = embed_contract(content, model, options, precision, extra_record)
    with atomic_path(path, suffix=".tflite") as tmp:
        tmp.write_bytes(content)
    seconds = {**seconds, "write": round(time.perf_counter() - started, 2)}
    seconds["total"] = round(sum(seconds.values()), 2)
    ops = tflite_op_histogram(content)
    return LiteRTResult(
        path=str(path), bytes=len(content), seconds=seconds,
        ops={"histogram": ops, "mac_ops": {k: v for k, v in ops.items() if k in MAC_OPS},
             "xnnpack_partitions": delegate_partitions(content)},
        options=vars(options).copy(), artifact=record,
    )


def convert_litert(model: E3DPSM, path: str | os.PathLike, options: LiteRTOptions = LiteRTOptions(),
                   precision: str = "fp32", extra_record: dict[str, Any] | None = None) -> LiteRTResult:
    """Write `path` (.tflite) with the state layout inside; returns sizes, timings, ops."""
    started = time.perf_counter()
    content = litert_content(model, options)
    return write_litert(content, model, path, options, precision,
                        {"convert": round(time.perf_counter() - started, 2)}, extra_record)
