"""`e3dpsm convert tensorrt`'s builder (export/tensorrt_build.py) on a stand-in for the tensorrt
Python API that records every call: the flags each precision sets, the one-stream optimisation
profile, the timing cache read and written back, the engine, its sidecar and the result, and
each refusal whole. That TensorRT builds and runs what this asks for is bench_tensorrt.py's
check on a GPU (docs/edge.md)."""
from __future__ import annotations

import sys
import types
from pathlib import Path

import onnx
import pytest

from _io_helpers import record_temporaries
from _toy_step_graph import STATE, toy_step_graph
from e3dpsm.errors import ConfigError, DataError
from e3dpsm.export.tensorrt_build import PRECISIONS, TensorRTOptions, build_engine
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.runtime.artifact_metadata import decode, sidecar_path
from e3dpsm.state import state_input_name, state_output_name


class Recorder:
    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.parse_errors: list[str] = []
        self.engine: bytes | None = b"ENGINE"
        self.cache_out = b"CACHE-v1"


def fake_tensorrt(rec: Recorder) -> types.ModuleType:
    trt = types.ModuleType("tensorrt")
    trt.__version__ = "10.9.0"

    class Logger:
        WARNING = "warning"

        def __init__(self, level):
            rec.calls.append(("logger", level))

    class Tensor:
        def __init__(self, name, shape):
            self.name, self.shape = name, shape

    class Network:
        inputs = [Tensor("lnes", (-1, 2, 2, 3)), Tensor("window_ms", (-1,)), Tensor(state_input_name(STATE), (-1, 3))]
        outputs = [Tensor("pose", (-1, 3)), Tensor(state_output_name(STATE), (-1, 3))]
        num_inputs, num_outputs = 3, 2

        def get_input(self, i):
            return self.inputs[i]

        def get_output(self, i):
            return self.outputs[i]

    class OnnxParser:
        def __init__(self, network, logger):
            self.num_errors = len(rec.parse_errors)

        def parse(self, data):
            rec.calls.append(("parse", len(data)))
            return not rec.parse_errors

        def get_error(self, i):
            return rec.parse_errors[i]

    class Profile:
        def set_shape(self, name, low, opt, high):
            rec.calls.append(("shape", name, tuple(low), tuple(opt), tuple(high)))

    class Cache:
        def __init__(self, data):
            self.data = data

        def serialize(self):
            return rec.cache_out

    class Config:
        def set_memory_pool_limit(self, pool, size):
            rec.calls.append(("pool", pool, size))

        def set_flag(self, flag):
            rec.calls.append(("flag", flag))

        def add_optimization_profile(self, profile):
            rec.calls.append(("profile",))

        def create_timing_cache(self, data):
            rec.calls.append(("cache in", bytes(data)))
            return Cache(data)

        def set_timing_cache(self, cache, ignore_mismatch):
            rec.calls.append(("cache set", ignore_mismatch))

        def get_timing_cache(self):
            return Cache(None)

    class Builder:
        def __init__(self, logger):
            assert isinstance(logger, Logger)

        def create_network(self, flags):
            rec.calls.append(("network", flags))
            return Network()

        def create_builder_config(self):
            return Config()

        def create_optimization_profile(self):
            return Profile()

        def build_serialized_network(self, network, config):
            rec.calls.append(("build",))
            return rec.engine

    trt.Logger, trt.Builder, trt.OnnxParser = Logger, Builder, OnnxParser
    trt.MemoryPoolType = types.SimpleNamespace(WORKSPACE="workspace")
    trt.BuilderFlag = types.SimpleNamespace(FP16="FP16", INT8="INT8")
    return trt


@pytest.fixture
def rec(monkeypatch) -> Recorder:
    recorder = Recorder()
    monkeypatch.setitem(sys.modules, "tensorrt", fake_tensorrt(recorder))
    return recorder


@pytest.fixture
def graphs(tmp_path) -> dict[str, Path]:
    fp32 = tmp_path / "step.onnx"
    onnx.save(toy_step_graph(), fp32)
    int8 = tmp_path / "step_int8.onnx"
    model = toy_step_graph()
    meta = GraphMetadata.from_onnx(model)
    GraphMetadata(states=meta.states, inputs=meta.inputs, outputs=meta.outputs, config=meta.config, joints=meta.joints,
                  quantization={"mode": "int8"}).write_to(model)
    onnx.save(model, int8)
    return {"fp32": fp32, "int8": int8}


@pytest.mark.parametrize("precision, flags", [("fp32", []), ("fp16", ["FP16"]), ("int8", ["FP16", "INT8"])])
def test_each_precision_sets_its_flags_and_one_stream_shapes(rec, graphs, tmp_path, precision, flags) -> None:
    source = graphs["int8" if precision == "int8" else "fp32"]
    result = build_engine(source, tmp_path / "out" / "step.engine", TensorRTOptions(precision, workspace_mb=3))
    names = [c[0] for c in rec.calls]
    assert names[:2] == ["logger", "network"] and rec.calls[0] == ("logger", "warning") and rec.calls[1] == ("network", 0)
    assert ("parse", source.stat().st_size) in rec.calls and ("pool", "workspace", 3 << 20) in rec.calls
    assert [c[1] for c in rec.calls if c[0] == "flag"] == flags
    assert [c[1:] for c in rec.calls if c[0] == "shape"] == [
        ("lnes", (1, 2, 2, 3), (1, 2, 2, 3), (1, 2, 2, 3)), ("window_ms", (1,), (1,), (1,)),
        (state_input_name(STATE), (1, 3), (1, 3), (1, 3))]
    assert names.index("profile") > max(i for i, n in enumerate(names) if n == "shape")
    assert ("cache in", b"") in rec.calls and ("cache set", False) in rec.calls and names[-1] == "build"
    engine = tmp_path / "out" / "step.engine"
    assert engine.read_bytes() == b"ENGINE" and result.path == str(engine) and result.bytes == 6
    meta, artifact = decode(sidecar_path(engine).read_text(encoding="utf-8"), "sidecar")
    assert meta == GraphMetadata.from_onnx(onnx.load(str(source)))
    assert artifact == result.artifact == {
        "format": "tensorrt", "precision": precision, "source": source.name,
        "inputs": ["lnes", "window_ms", state_input_name(STATE)], "outputs": ["pose", state_output_name(STATE)],
        "versions": {"tensorrt": "10.9.0"}}
    assert (tmp_path / "out" / "timing.cache").read_bytes() == b"CACHE-v1"
    assert result.timing_cache == {"path": str(tmp_path / "out" / "timing.cache"), "reused_bytes": 0}
    assert result.options == {"precision": precision, "workspace_mb": 3}
    assert set(result.seconds) == {"build", "total"} and 0 <= result.seconds["build"] <= result.seconds["total"]
    assert result.to_dict()["artifact"] == artifact
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["step.engine", "step.engine.json", "timing.cache"]


def test_the_timing_cache_is_reused_from_its_folder(rec, graphs, tmp_path) -> None:
    caches = tmp_path / "caches"
    caches.mkdir()
    (caches / "timing.cache").write_bytes(b"OLD-CACHE")
    result = build_engine(graphs["fp32"], tmp_path / "e" / "step.engine", cache_dir=caches)
    assert ("cache in", b"OLD-CACHE") in rec.calls and result.timing_cache["reused_bytes"] == 9
    assert (caches / "timing.cache").read_bytes() == b"CACHE-v1" and not (tmp_path / "e" / "timing.cache").exists()
    assert result.options == {"precision": "fp32", "workspace_mb": 1024}
    assert ("pool", "workspace", 1024 << 20) in rec.calls


def test_refusals_are_one_line_and_write_nothing(rec, graphs, tmp_path, monkeypatch) -> None:
    out = tmp_path / "out" / "step.engine"

    def refused(error, message, source=graphs["fp32"], options=TensorRTOptions()):
        with pytest.raises(error) as caught:
            build_engine(source, out, options)
        assert str(caught.value) == message and not out.parent.exists()

    assert PRECISIONS == ("fp32", "fp16", "int8")
    refused(ConfigError, "unknown TensorRT precision 'bf16'; choose one of fp32, fp16, int8",
            options=TensorRTOptions("bf16"))
    refused(DataError, f"model {tmp_path / 'missing.onnx'} does not exist", source=tmp_path / "missing.onnx")
    refused(ConfigError, f"{graphs['fp32']} is an fp32 graph: --int8 builds from the QDQ graph of `e3dpsm quantize`",
            options=TensorRTOptions("int8"))
    rec.parse_errors = ["In node 3: unsupported op", "x" * 400]
    refused(DataError, f"TensorRT cannot parse {graphs['fp32']}: " + ("In node 3: unsupported op; " + "x" * 400)[:300])
    rec.parse_errors, rec.engine = [], None
    refused(DataError, f"TensorRT could not build an engine from {graphs['fp32']} (its log above says why)")
    monkeypatch.setitem(sys.modules, "tensorrt", None)
    refused(ConfigError, 'tensorrt is not installed (to build TensorRT engines): pip install -e ".[tensorrt]"')


def test_timings_temporaries_and_the_records_defaults(rec, graphs, tmp_path, monkeypatch) -> None:
    import dataclasses

    from e3dpsm.export import tensorrt_build

    clock = iter([100.0, 101.23456, 102.98765])
    monkeypatch.setattr(tensorrt_build.time, "perf_counter", lambda: next(clock))
    temporaries = record_temporaries(monkeypatch, tensorrt_build)
    result = build_engine(graphs["fp32"], tmp_path / "step.engine")
    assert result.seconds == {"build": 1.23, "total": 2.99}
    # Hidden temporaries that keep their file's extension: a crashed build's leftovers say what they were.
    assert temporaries[0].startswith(".step.engine.") and temporaries[0].endswith(".engine")
    assert temporaries[1].startswith(".timing.cache.") and temporaries[1].endswith(".cache") and len(temporaries) == 2
    with pytest.raises(dataclasses.FrozenInstanceError):
        TensorRTOptions().precision = "int8"
    bare = tensorrt_build.TensorRTResult(path="p", bytes=1, seconds={}, timing_cache={}, options={})
    assert bare.to_dict()["artifact"] == {}
