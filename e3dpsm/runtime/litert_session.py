"""Drive a LiteRT step model (`.tflite`, `e3dpsm convert litert`) with ai-edge-litert's
interpreter and numpy alone: no torch, as on a phone. Extra: `pip install -e ".[litert]"`.

The state layout comes from the model's own metadata buffer `e3dpsm`
(runtime/artifact_metadata.py); inputs and outputs are bound by name through the model's
signature, whose names are the ONNX graph's."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from e3dpsm.errors import DataError
from e3dpsm.graph_metadata import MetadataError
from e3dpsm.runtime.artifact_metadata import EMBEDDED_NAME, decode
from e3dpsm.runtime.artifact_session import ArtifactSession
from e3dpsm.utils.extras import require

FORMAT = "litert"


def read_tflite(path: str | os.PathLike) -> bytes:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"model {path} does not exist")
    content = path.read_bytes()
    if content[4:8] != b"TFL3":
        raise DataError(f"{path} is not a TFLite model (no TFL3 identifier)")
    return content


def tflite_metadata(path: str | os.PathLike, content: bytes):
    """(GraphMetadata, artifact record) from the model's `e3dpsm` metadata buffer."""
    from e3dpsm.runtime.tflite_metadata import read_metadata

    try:
        entries = read_metadata(content)
    except Exception as exc:  # a flatbuffer the schema cannot walk
        raise DataError(f"{path} is not a readable TFLite model: {str(exc).splitlines()[0][:200]}") from exc
    if EMBEDDED_NAME not in entries:
        raise MetadataError(f"{path} carries no e3dpsm state layout (no '{EMBEDDED_NAME}' metadata buffer); "
                            "write it with `e3dpsm convert litert`")
    return decode(entries[EMBEDDED_NAME].decode("utf-8"), str(path))


class LiteRTStepSession(ArtifactSession):
    runtime = FORMAT

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None) -> None:
        interpreter_module = require("ai_edge_litert.interpreter", "to run .tflite models")
        content = read_tflite(path)
        meta, self.artifact = tflite_metadata(path, content)
        try:
            interpreter = interpreter_module.Interpreter(model_content=content, num_threads=threads)
            self._runner = interpreter.get_signature_runner()
        except (ValueError, RuntimeError) as exc:
            raise DataError(f"LiteRT cannot load {path}: {str(exc).splitlines()[0][:300]}") from exc
        self._interpreter = interpreter
        self._bind(path, meta, list(self._runner.get_input_details()), list(self._runner.get_output_details()))

    def _run_one(self, feeds: Mapping[str, np.ndarray]) -> dict[str, Any]:
        return self._runner(**feeds)
