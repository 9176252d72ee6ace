"""`e3dpsm convert tensorrt`: an ONNX step graph (`e3dpsm export`, or the QDQ graph of
`e3dpsm quantize`) as a serialized TensorRT engine (`step.engine`) built with the tensorrt
Python API for batch 1, fp32, fp16 (`--fp16`) or INT8 (`--int8`: the Q/DQ nodes of the
graph give the scales, TensorRT's explicit quantisation), the builder's timing cache kept
beside it (`timing.cache`, reused by the next build on the same GPU).

An engine has no room for metadata: the graph's contract goes to the sidecar
`step.engine.json` (runtime/artifact_metadata.py), which the runner reads.

UNTESTED on hardware: written against the TensorRT 10 Python API on a machine without a
GPU; tests skip without one, and benchmarks/bench_tensorrt.py is the check to run the day
a GPU is there (docs/edge.md)."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from e3dpsm.errors import ConfigError, DataError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.runtime.artifact_metadata import encode, sidecar_path
from e3dpsm.utils.extras import require
from e3dpsm.utils.io import atomic_path, write_text_atomic

FORMAT = "tensorrt"
PRECISIONS = ("fp32", "fp16", "int8")
TIMING_CACHE = "timing.cache"


@dataclass(frozen=True)
class TensorRTOptions:
    precision: str = "fp32"
    workspace_mb: int = 1024


@dataclass
class TensorRTResult:
    path: str
    bytes: int
    seconds: dict[str, float]
    timing_cache: dict[str, Any]
    options: dict[str, Any]
    artifact: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dict(vars(self))


def _parse(trt: Any, builder: Any, logger: Any, onnx_path: Path) -> Any:
    network = builder.create_network(0)
    parser = trt.OnnxParser(network, logger)
    if not parser.parse(onnx_path.read_bytes()):
        errors = "; ".join(str(parser.get_error(i)) for i in range(parser.num_errors))
        raise DataError(f"TensorRT cannot parse {onnx_path}: {errors[:300]}")
    return network


def _config(trt: Any, builder: Any, network: Any, options: TensorRTOptions, cache_bytes: bytes) -> Any:
    config = builder.create_builder_config()
    config.set_memory_pool_limit(trt.MemoryPoolType.WORKSPACE, options.workspace_mb << 20)
    if options.precision in ("fp16", "int8"):
        config.set_flag(trt.BuilderFlag.FP16)  # int8: layers without Q/DQ run fp16
    if options.precision == "int8":
        config.set_flag(trt.BuilderFlag.INT8)
    profile = builder.create_optimization_profile()
    for i in range(network.num_inputs):  # the graph's dynamic batch axis, fixed to one stream
        tensor = network.get_input(i)
        shape = [1 if d < 0 else d for d in tensor.shape]
        profile.set_shape(tensor.name, shape, shape, shape)
    config.add_optimization_profile(profile)
    cache = config.create_timing_cache(cache_bytes)
    config.set_timing_cache(cache, ignore_mismatch=False)
    return config


def build_engine(onnx_path: str | os.PathLike, path: str | os.PathLike,
                 options: TensorRTOptions = TensorRTOptions(), cache_dir: str | os.PathLike | None = None) -> TensorRTResult:
    """Write `path` (.engine), its sidecar and the timing cache (in `cache_dir`, default beside it)."""
    import onnx

    trt = require("tensorrt", "to build TensorRT engines")
    if options.precision not in PRECISIONS:
        raise ConfigError(f"unknown TensorRT precision {options.precision!r}; choose one of {', '.join(PRECISIONS)}")
    onnx_path, path = Path(onnx_path), Path(path)
    if not onnx_path.is_file():
        raise DataError(f"model {onnx_path} does not exist")
    meta = GraphMetadata.from_onnx(onnx.load(str(onnx_path), load_external_data=False), source=str(onnx_path))
    if options.precision == "int8" and not meta.quantization:
        raise ConfigError(f"{onnx_path} is an fp32 graph: --int8 builds from the QDQ graph of `e3dpsm quantize`")
    cache_file = Path(cache_dir or path.parent) / TIMING_CACHE
    cache_bytes = cache_file.read_bytes() if cache_file.is_file() else b""
    started = time.perf_counter()
    logger = trt.Logger(trt.Logger.WARNING)
    builder = trt.Builder(logger)
    network = _parse(trt, builder, logger, onnx_path)
    config = _config(trt, builder, network, options, cache_bytes)
    engine = builder.build_serialized_network(network, config)
    if engine is None:
        raise DataError(f"TensorRT could not build an engine from {onnx_path} (its log above says why)")
    built = time.perf_counter()
    record = {"format": FORMAT, "precision": options.precision, "source": onnx_path.name,
              "inputs": [network.get_input(i).name for i in range(network.num_inputs)],
              "outputs": [network.get_output(i).name for i in range(network.num_outputs)],
              "versions": {"tensorrt": trt.__version__}}
    with atomic_path(path, suffix=".engine") as tmp:
        tmp.write_bytes(bytes(engine))
    write_text_atomic(sidecar_path(path), encode(meta, record))
    with atomic_path(cache_file, suffix=".cache") as tmp:
        tmp.write_bytes(bytes(config.get_timing_cache().serialize()))
    return TensorRTResult(
        path=str(path), bytes=path.stat().st_size, options=vars(options).copy(), artifact=record,
        seconds={"build": round(built - started, 2), "total": round(time.perf_counter() - started, 2)},
        timing_cache={"path": str(cache_file), "reused_bytes": len(cache_bytes)},
    )
