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


def convert_litert(model: E3DPSM, path: str | os.PathLike, options: LiteRTOptions = LiteRTOptions(),
                   precision: str = "fp32", quant_config: Any = None,
                   extra_record: dict[str, Any] | None = None) -> LiteRTResult:
    """Write `path` (.tflite) with the state layout inside; returns sizes, timings, ops."""
    litert_torch = require("litert_torch", "to write .tflite models")
    require("ai_edge_litert", "to write .tflite models")
    from e3dpsm.runtime.tflite_metadata import with_metadata

    meta, record = artifact_contract(model, FORMAT, precision, options.attention_form,
                                     ("litert-torch", "ai-edge-litert"), extra_record)
    wrapper = NamedStepGraph(model).eval()  # the wrapper has no layers of its own; eval() says so to the converter
    started = time.perf_counter()
    with export_ready(model, options.attention_form):
        converted = litert_torch.convert(wrapper, sample_kwargs=wrapper.example_kwargs(), quant_config=quant_config)
    converted_at = time.perf_counter()
    content = with_metadata(converted.model_content(), EMBEDDED_NAME, encode(meta, record).encode("utf-8"))
    with atomic_path(path, suffix=".tflite") as tmp:
        tmp.write_bytes(content)
    done = time.perf_counter()
    ops = tflite_op_histogram(content)
    return LiteRTResult(
        path=str(path), bytes=len(content),
        seconds={"convert": round(converted_at - started, 2), "write": round(done - converted_at, 2),
                 "total": round(done - started, 2)},
        ops={"histogram": ops, "mac_ops": {k: v for k, v in ops.items() if k in MAC_OPS},
             "xnnpack_partitions": delegate_partitions(content)},
        options=vars(options).copy(), artifact=record,
    )
