"""An ONNX Runtime pre-optimised copy of a step graph, saved beside the portable one.

ONNX Runtime rewrites every graph it loads (constant folding, operator fusions, and at level
"all" the CPU provider's NCHWc layout). Saving its result (`SessionOptions.
optimized_model_filepath`) lets an edge device skip that work at start-up: load the saved
file with graph optimisations off. The file is specific to the ONNX Runtime version and the
execution provider that wrote it (it may hold com.microsoft operators): the portable
step.onnx stays the reference.
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from e3dpsm.errors import ConfigError

ORT_LEVELS = ("basic", "extended", "all")


def write_ort_optimized(
    source: str | os.PathLike, target: str | os.PathLike, level: str = "extended",
) -> dict[str, Any]:
    """Write ONNX Runtime's CPU-optimised form of `source` to `target` (atomically, via a
    temporary name); returns what export.json records about it."""
    import onnxruntime as ort

    from e3dpsm.utils.io import atomic_path

    if level not in ORT_LEVELS:
        raise ConfigError(f"unknown ONNX Runtime optimisation level {level!r}; choose from {ORT_LEVELS}")
    levels = {"basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
              "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
              "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL}
    t0 = time.perf_counter()
    with atomic_path(target, suffix=".onnx") as tmp_path:
        options = ort.SessionOptions()
        options.graph_optimization_level = levels[level]
        options.optimized_model_filepath = str(tmp_path)
        ort.InferenceSession(str(source), options, providers=["CPUExecutionProvider"])
    return {
        "path": Path(target).name, "level": level, "onnxruntime": ort.__version__,
        "provider": "CPUExecutionProvider", "bytes": Path(target).stat().st_size,
        "seconds": round(time.perf_counter() - t0, 3),
        "note": "specific to this ONNX Runtime version and execution provider; load it with graph "
                "optimisations disabled; the portable graph is the reference",
    }
