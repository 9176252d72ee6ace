"""The step graph's contract (e3dpsm.graph_metadata: state layout, inputs, outputs, config,
joints) carried by artifacts other than ONNX graphs. Torch-free.

Each format keeps the same key -> JSON-string map that an ONNX graph keeps in its
`metadata_props`, as one JSON object:
- ExecuTorch `.pte`: a constant method `e3dpsm_metadata` returning the object as a string;
- LiteRT `.tflite`: a model metadata buffer named `e3dpsm` (runtime/tflite_metadata.py);
- Core ML `.mlpackage`: the map itself as user-defined metadata;
- formats with no place for it (a TensorRT engine): a sidecar `<artifact>.json` beside it.

`KEY_ARTIFACT` adds what wrote the artifact (format, precision, the converter's versions),
which a runner checks before trusting the file.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

from e3dpsm.graph_metadata import GraphMetadata, MetadataError

KEY_ARTIFACT = "e3dpsm.artifact"
EMBEDDED_NAME = "e3dpsm"  # TFLite metadata buffer name
PTE_METHOD = "e3dpsm_metadata"  # ExecuTorch constant method
TAPS_METHOD = "e3dpsm_taps"  # an INT8 .pte's taps program: its taps (export/executorch_taps.py)
SIDECAR_SUFFIX = ".json"
# What `e3dpsm convert FORMAT --out DIR` writes in DIR: the artifact under this name, and its record.
CONVERTED_NAMES = {"executorch": "step.pte", "litert": "step.tflite", "coreml": "step.mlpackage"}
CONVERT_RECORD = "convert.json"


def encode(meta: GraphMetadata, artifact: Mapping[str, Any]) -> str:
    """The metadata and the artifact record as one JSON object of strings, keys sorted at both
    levels: the same contract gives the same bytes, whatever order a converter built it in."""
    return json.dumps({**meta.to_props(), KEY_ARTIFACT: json.dumps(dict(artifact), sort_keys=True)}, sort_keys=True)


def decode(text: str | bytes, source: str) -> tuple[GraphMetadata, dict[str, Any]]:
    """(metadata, artifact record) from `encode`'s text; MetadataError when broken."""
    try:
        props = json.loads(text)
        if not isinstance(props, dict) or not all(isinstance(v, str) for v in props.values()):
            raise ValueError("expected an object of strings")
        artifact = json.loads(props.pop(KEY_ARTIFACT, "{}"))
    except ValueError as exc:
        raise MetadataError(f"{source} carries broken e3dpsm metadata: {exc}") from exc
    return GraphMetadata.from_props(props, source), artifact


def encode_taps(taps: Sequence[Mapping[str, Any]]) -> str:
    """A taps program's taps (`{"tap": name, "segment": operators}`), in the order it returns
    them, as TAPS_METHOD's JSON."""
    return json.dumps([dict(t) for t in taps])


def decode_taps(text: str, source: str) -> list[dict[str, Any]]:
    """The taps TAPS_METHOD returns, checked (a ValueError naming `source` otherwise)."""
    try:
        taps = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{source}: its {TAPS_METHOD} is not JSON ({exc})") from exc
    if not isinstance(taps, list) or not taps or not all(
            isinstance(t, dict) and isinstance(t.get("tap"), str) and isinstance(t.get("segment"), list)
            for t in taps):
        raise ValueError(f"{source}: its {TAPS_METHOD} is not a list of taps (each a name and its segment)")
    return taps


def sidecar_path(path: str | os.PathLike) -> Path:
    path = Path(path)
    return path.with_name(path.name + SIDECAR_SUFFIX)


def read_sidecar(path: str | os.PathLike) -> tuple[GraphMetadata, dict[str, Any]]:
    sidecar = sidecar_path(path)
    if not sidecar.is_file():
        raise MetadataError(f"{path} has no state layout: {sidecar.name} is not beside it (the converter writes "
                            "it; copy it with the artifact)")
    return decode(sidecar.read_text(encoding="utf-8"), str(sidecar))
