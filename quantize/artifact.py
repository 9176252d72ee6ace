"""Write a quantised graph as an e3dpsm artifact: the source's metadata plus what was
quantised and how, an IR version ONNX Runtime 1.31 reads, default-domain ops only."""
from __future__ import annotations

import os
from typing import Any

import onnx

from e3dpsm.errors import E3DPSMError
from e3dpsm.export.onnx_export import ALLOWED_DOMAINS, foreign_ops
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.export.openvino_compat import openvino_compatible
from e3dpsm.utils.io import atomic_path

MAX_IR_VERSION = 10  # ONNX Runtime 1.31 reads up to 13; 10 keeps older runtimes working too


class QuantizeError(E3DPSMError):
    """The quantisation tools produced a graph that does not meet the artifact contract."""


def finalize(model: onnx.ModelProto, source_meta: GraphMetadata, info: dict[str, Any]) -> onnx.ModelProto:
    """Set metadata and IR version in place; raise if the graph left the default domain.
    Every artifact and search trial passes here, so each also gets the Reshape guards
    OpenVINO needs (openvino_compat.py; ONNX Runtime's numbers unchanged)."""
    foreign = foreign_ops(model)
    if foreign:
        raise QuantizeError(f"quantised graph uses non-standard operators {foreign}")
    openvino_compatible(model)
    opsets = [o for o in model.opset_import if o.domain in ALLOWED_DOMAINS]
    needed = onnx.helper.find_min_ir_version_for(opsets, ignore_unknown=True)
    if needed > MAX_IR_VERSION:
        raise QuantizeError(f"quantised graph needs IR {needed}, above the supported {MAX_IR_VERSION}")
    # The tools write the IR of the installed onnx (14 for onnx 1.23), which ORT 1.31 refuses.
    model.ir_version = max(needed, min(model.ir_version, MAX_IR_VERSION))
    source_meta.with_quantization(info).write_to(model)
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
