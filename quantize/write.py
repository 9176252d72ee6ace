"""Passes 4 and 5: round the weights, write the graph.

Every graph the quantiser makes, each search trial and the artifact, comes from `build_int8`:
ONNX Runtime's QDQ quantiser over the prepared graph with the calibration cache (no new
calibration per trial), the plan's float and 16-bit nodes, learned ranges where given, then
the chosen weight integers and the Q/DQ pairs on outputs no quantised op reads removed.
`write_artifact` adds what a runtime needs to run it alone (metadata, IR version) and makes it
smaller (compaction, retiled constants).
"""
from __future__ import annotations

import os
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import onnx

from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.onnx_constants import retile_constants
from e3dpsm.quantize.adaround import AdaRoundConfig, adaround_weights, apply_rounding
from e3dpsm.quantize.artifact import finalize, save_model
from e3dpsm.onnx_precision import compute_precisions, out_of_8_bits, precision_counts
from e3dpsm.quantize.compact import compact_qdq, graph_names
from e3dpsm.quantize.outputs import FLOAT_OUTPUTS, dequantised_outputs
from e3dpsm.quantize.prepare import Calibration, PreparedGraph
from e3dpsm.quantize.static import quantize_int8


@dataclass(frozen=True)
class Rounding:
    """Pass 4: the weights' integers (AdaRound's where chosen), written into every graph after."""

    method: str
    rounded: Mapping[str, Any] = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        ratios = [r.output_error_ratio for r in self.rounded.values()]
        return {"method": self.method, "weights": len(self.rounded), "seconds": round(self.seconds, 2),
                **({"median_output_error_ratio": float(np.median(ratios)), **asdict(AdaRoundConfig())}
                   if ratios else {})}


def float_nodes_of(prepared: PreparedGraph, floats: Sequence[str]) -> list[str]:
    """The nodes a plan keeps float: a fixed `--exclude`'s, else the recurrent groups and `floats`."""
    base = prepared.fixed if prepared.fixed is not None else prepared.recurrent
    return list(dict.fromkeys([*base, *floats]))


def build_int8(prepared: PreparedGraph, calibration: Calibration, floats: Sequence[str] = (),
               int16: Sequence[str] = (), *, float_outputs: str = "matmul",
               rounding: Rounding | None = None) -> onnx.ModelProto:
    """The QDQ graph of the plan (`floats` back to float, `int16` at 16-bit activations)."""
    with tempfile.TemporaryDirectory(prefix="e3dpsm-int8-") as work:
        path = Path(work) / "int8.onnx"
        quantize_int8(prepared.path, path, prepared.config, exclude=float_nodes_of(prepared, floats),
                      cache=calibration.cache, learned=calibration.learned, int16_nodes=int16)
        model = onnx.load(str(path))
    if rounding is not None and rounding.rounded:
        apply_rounding(model, rounding.rounded)
    dequantised_outputs(model, FLOAT_OUTPUTS[float_outputs], prepared.config.op_types)
    return model


def round_weights(prepared: PreparedGraph, calibration: Calibration, method: str,
                  threads: int | None = None) -> Rounding:
    """AdaRound's integers for every 8-bit weight, chosen at ONNX Runtime's own scales (read off
    a graph with every Conv/MatMul/Gemm quantised) against each layer's output on the
    calibration frames; nothing for nearest rounding, which the quantiser does itself."""
    if method == "nearest":
        return Rounding("nearest")
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="e3dpsm-adaround-") as work:
        probe = Path(work) / "probe.onnx"
        quantize_int8(prepared.path, probe, prepared.config, exclude=[], cache=calibration.cache)
        rounded = adaround_weights(onnx.load(str(prepared.path)), onnx.load(str(probe)), calibration.feeds,
                                   threads=threads)
    return Rounding(method, rounded, time.perf_counter() - started)


@dataclass(frozen=True)
class Written:
    """Pass 5: the artifact on disk and what it computes in."""

    path: Path
    bytes: int
    source_bytes: int
    precision: Mapping[str, str]   # Conv/MatMul/Gemm -> int8 | int16 | float (census.py)
    saved: Mapping[str, Any]

    @property
    def size_ratio(self) -> float:
        return self.bytes / self.source_bytes

    def to_dict(self) -> dict[str, Any]:
        return {"path": self.path.name, "bytes": self.bytes, "source_bytes": self.source_bytes,
                "size_ratio": self.size_ratio, "compute_precision": precision_counts(dict(self.precision)),
                "compute_nodes_out_of_8_bits": out_of_8_bits(dict(self.precision)), "saved": dict(self.saved)}

    @property
    def bytes_saved(self) -> int:
        return sum(int(part.get("bytes_saved", 0)) for part in self.saved.values())

    def report_lines(self) -> list[str]:
        counts = precision_counts(dict(self.precision))
        return [f"Artifact `{self.path.name}`: {self.bytes / 1e6:.3f} MB against the fp32 graph's "
                f"{self.source_bytes / 1e6:.3f} MB ({self.size_ratio:.3f}x), {self.bytes_saved / 1e3:.0f} kB less than "
                "the quantiser wrote it (names shortened, equal constants shared, repeating constants retiled). "
                "Conv/MatMul/Gemm, recurrent groups included: "
                + ", ".join(f"{n} {label}" for label, n in counts.items() if n) + ".", ""]


def write_artifact(model: onnx.ModelProto, source: onnx.ModelProto, meta: GraphMetadata, info: Mapping[str, Any],
                   path: Path, source_bytes: int) -> Written:
    """The graph as an e3dpsm artifact at `path` (atomically): the source's metadata plus
    `info`, an IR version ONNX Runtime 1.31 reads, the quantiser's names shortened and equal
    constants shared (compact.py), repeating constants retiled (onnx_constants.py)."""
    finalize(model, meta, dict(info))
    compaction = compact_qdq(model, keep=graph_names(source))
    retiled = retile_constants(model)
    size = save_model(model, path)
    return Written(path, size, source_bytes, compute_precisions(model),
                   {"compaction": compaction.to_dict(), "retiled_constants": retiled.to_dict()})


def scratch_path(folder: str | os.PathLike, label: str) -> Path:
    safe = "".join(c if c.isalnum() else "_" for c in label)
    return Path(tempfile.mkstemp(prefix=f"trial_{safe}_", suffix=".onnx", dir=folder)[1])
