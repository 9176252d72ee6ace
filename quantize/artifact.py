"""Write a quantised graph as an e3dpsm artifact: the source's metadata plus what was
quantised and how, an IR version ONNX Runtime 1.31 reads, default-domain ops only."""
from __future__ import annotations

import os
from typing import Any

import onnx

from e3dpsm.errors import E3DPSMError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.utils.io import atomic_path

MAX_IR_VERSION = 10  # ONNX Runtime 1.31 reads up to 13; 10 keeps older runtimes working too
ALLOWED_DOMAINS = ("", "ai.onnx")


class QuantizeError(E3DPSMError):
    """The quantisation tools produced a graph that does not meet the artifact contract."""


def finalize(model: onnx.ModelProto, source_meta: GraphMetadata, info: dict[str, Any]) -> onnx.ModelProto:
    """Set metadata and IR version in place; raise if the graph left the default domain."""
    foreign = sorted({f"{n.domain}::{n.op_type}" for n in model.graph.node if n.domain not in ALLOWED_DOMAINS})
    if foreign:
        raise QuantizeError(f"quantised graph uses non-standard operators {foreign}")
    opsets = [o for o in model.opset_import if o.domain in ALLOWED_DOMAINS]
    needed = onnx.helper.find_min_ir_version_for(opsets, ignore_unknown=True)
    if needed > MAX_IR_VERSION:
        raise QuantizeError(f"quantised graph needs IR {needed}, above the supported {MAX_IR_VERSION}")
    # The tools write the IR of the installed onnx (14 for onnx 1.23), which ORT 1.31 refuses.
    model.ir_version = max(needed, min(model.ir_version, MAX_IR_VERSION))
    del model.metadata_props[:]
    for key, value in source_meta.with_quantization(info).to_props().items():
        model.metadata_props.add(key=key, value=value)
    model.producer_name = "e3dpsm"
    return model


def save_model(model: onnx.ModelProto, path: str | os.PathLike) -> int:
    """Checked, atomic save; returns the file size in bytes."""
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as exc:
        raise QuantizeError(f"quantised graph fails the ONNX checker: {str(exc).splitlines()[0]}") from exc
    with atomic_path(path, suffix=".onnx") as tmp:
        onnx.save(model, str(tmp))
    return os.path.getsize(path)


def op_counts(model: onnx.ModelProto) -> dict[str, int]:
    counts: dict[str, int] = {}
    for node in model.graph.node:
        counts[node.op_type] = counts.get(node.op_type, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: -kv[1]))
