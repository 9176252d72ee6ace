"""Drive a TensorRT step engine (`.engine`, `e3dpsm convert tensorrt`) on an NVIDIA GPU with
the tensorrt runtime and cuda-python (`pip install -e ".[tensorrt]"`), states carried on the
host like every other runner. The state layout is the sidecar `step.engine.json`.

UNTESTED on hardware (no GPU where it was written): benchmarks/bench_tensorrt.py is the
check to run first on a machine with one (docs/edge.md)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from e3dpsm.errors import ConfigError, DataError
from e3dpsm.runtime.artifact_metadata import read_sidecar
from e3dpsm.runtime.artifact_session import ArtifactSession
from e3dpsm.utils.extras import require

FORMAT = "tensorrt"


def _check(result: Any) -> Any:
    """cuda-python returns (error, *values); raise on an error."""
    error, *values = result if isinstance(result, tuple) else (result,)
    if int(error) != 0:
        raise ConfigError(f"CUDA call failed: {error}")
    return values[0] if len(values) == 1 else values


class TensorRTStepSession(ArtifactSession):
    runtime = FORMAT

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None) -> None:
        trt = require("tensorrt", "to run TensorRT engines")
        self._cudart = require("cuda.bindings.runtime", "to run TensorRT engines")
        if not Path(path).is_file():
            raise DataError(f"model {path} does not exist")
        meta, self.artifact = read_sidecar(path)
        engine = trt.Runtime(trt.Logger(trt.Logger.WARNING)).deserialize_cuda_engine(Path(path).read_bytes())
        if engine is None:
            raise DataError(f"TensorRT cannot load {path}: built by another TensorRT version or for another GPU")
        self._engine, self._context = engine, engine.create_execution_context()
        names = [engine.get_tensor_name(i) for i in range(engine.num_io_tensors)]
        is_input = {n: engine.get_tensor_mode(n) == trt.TensorIOMode.INPUT for n in names}
        self._bind(path, meta, [n for n in names if is_input[n]], [n for n in names if not is_input[n]])
        self._stream = _check(self._cudart.cudaStreamCreate())
        self._device: dict[str, int] = {}

    def _buffer(self, name: str, nbytes: int) -> int:
        if name not in self._device:
            self._device[name] = _check(self._cudart.cudaMalloc(nbytes))
        return self._device[name]

    def _run_one(self, feeds: Mapping[str, np.ndarray]) -> dict[str, Any]:
        cudart, copy = self._cudart, self._cudart.cudaMemcpyKind
        for name in self._inputs:
            value = np.ascontiguousarray(feeds[name], dtype=np.float32)
            self._context.set_input_shape(name, value.shape)
            pointer = self._buffer(name, value.nbytes)
            _check(cudart.cudaMemcpyAsync(pointer, value.ctypes.data, value.nbytes, copy.cudaMemcpyHostToDevice,
                                          self._stream))
            self._context.set_tensor_address(name, pointer)
        results = {}
        for name in self._outputs:
            results[name] = np.empty(tuple(self._context.get_tensor_shape(name)), np.float32)
            self._context.set_tensor_address(name, self._buffer(name, results[name].nbytes))
        self._context.execute_async_v3(self._stream)
        for name, value in results.items():
            _check(cudart.cudaMemcpyAsync(value.ctypes.data, self._device[name], value.nbytes,
                                          copy.cudaMemcpyDeviceToHost, self._stream))
        _check(cudart.cudaStreamSynchronize(self._stream))
        return results
