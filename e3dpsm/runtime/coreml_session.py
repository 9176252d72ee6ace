"""Drive a Core ML step program (`.mlpackage`, `e3dpsm convert coreml`) with coremltools'
prediction API, which exists on macOS only (Core ML is Apple's framework). Elsewhere the
runner refuses with the reason; benchmarks/bench_coreml.py runs parity and Hz on a Mac.

The state layout is the package's user-defined metadata `e3dpsm`; an output the package
keeps once because it is the same tensor as another (metadata `output_aliases`) is copied."""
from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from e3dpsm.errors import ConfigError, DataError
from e3dpsm.graph_metadata import MetadataError
from e3dpsm.runtime.artifact_metadata import EMBEDDED_NAME, decode
from e3dpsm.runtime.artifact_session import ArtifactSession
from e3dpsm.utils.extras import require

FORMAT = "coreml"


def coreml_unavailable_reason() -> str | None:
    if platform.system() != "Darwin":
        return f"Core ML predicts on macOS only (this is {platform.system()}); convert here, run on a Mac"
    return None


def package_metadata(path: str | os.PathLike, package: Any):
    text = package.user_defined_metadata.get(EMBEDDED_NAME)
    if text is None:
        raise MetadataError(f"{path} carries no e3dpsm state layout (user-defined metadata '{EMBEDDED_NAME}'); "
                            "write it with `e3dpsm convert coreml`")
    return decode(text, str(path))


class CoreMLStepSession(ArtifactSession):
    runtime = FORMAT

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None) -> None:
        ct = require("coremltools", "to run .mlpackage programs")
        if not Path(path).is_dir():
            raise DataError(f"model {path} does not exist (an .mlpackage is a folder)")
        reason = coreml_unavailable_reason()
        if reason:
            raise ConfigError(reason)
        self._model = ct.models.MLModel(str(path))  # threads: Core ML schedules its own compute units
        meta, self.artifact = package_metadata(path, self._model)
        self._aliases: dict[str, str] = dict(self.artifact.get("output_aliases", {}))
        description = self._model.get_spec().description
        outputs = [o.name for o in description.output] + list(self._aliases)
        self._bind(path, meta, [i.name for i in description.input], outputs)

    def _run_one(self, feeds: Mapping[str, np.ndarray]) -> dict[str, Any]:
        named = {k: np.asarray(v, dtype=np.float32) for k, v in self._model.predict(dict(feeds)).items()}
        named.update({alias: named[source] for alias, source in self._aliases.items()})
        return named
