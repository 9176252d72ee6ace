"""The TensorRT and Core ML step sessions (runtime/tensorrt_session.py, coreml_session.py),
which need a GPU or a Mac to run for real, on stand-ins for their libraries: a fake `tensorrt`
and `cuda.bindings.runtime` whose "device" is host memory and whose engine computes the toy
step, and a fake `coremltools` whose model predicts it. What is tested is the sessions' own
work: what they bind and check, every copy to and from the device and the buffers they keep,
the Core ML output aliases, and each refusal whole. That the real libraries behave as these
stand-ins do is what benchmarks/bench_tensorrt.py and bench_coreml.py check on the hardware."""
from __future__ import annotations

import ctypes
import sys
import types

import numpy as np
import pytest

from _golden_fakes import FRAME, STATE, STATE_SHAPE
from e3dpsm.errors import ConfigError, DataError, InputError
from e3dpsm.graph_metadata import GraphMetadata, MetadataError
from e3dpsm.runtime.artifact_metadata import EMBEDDED_NAME, encode, sidecar_path
from e3dpsm.state import StateSpec, state_input_name, state_output_name

S_IN, S_OUT = state_input_name(STATE), state_output_name(STATE)
META = GraphMetadata(states=(StateSpec(STATE, STATE_SHAPE),),
                     inputs={"frame": {"name": "lnes", "shape": [1, *FRAME]}, "window": {"name": "window_ms", "shape": [1]}},
                     outputs=[{"name": "pose"}], config={"variant": "toy"}, joints=[f"j{i}" for i in range(16)])


def toy_step(lnes, window, state) -> dict[str, np.ndarray]:
    window = np.asarray(window, np.float32).reshape(-1)
    return {"pose": (2 * lnes + window[0]).astype(np.float32), S_OUT: (state + window[0]).astype(np.float32)}


# --- TensorRT -------------------------------------------------------------------------------

class CudaError(int):
    """cuda-python's error enums convert to int (0: success) and print by name."""

    def __str__(self) -> str:
        return "cudaSuccess" if self == 0 else f"cudaErrorFake({int(self)})"


class FakeCudart(types.ModuleType):
    """cuda.bindings.runtime with host memory as the device: (error, value) tuples as cuda-python's."""

    class cudaMemcpyKind:
        cudaMemcpyHostToDevice, cudaMemcpyDeviceToHost = "H2D", "D2H"

    def __init__(self, fail: str | None = None) -> None:
        super().__init__("cuda.bindings.runtime")
        self.memory: dict[int, bytearray] = {}
        self.calls: list[tuple] = []
        self.fail = fail

    def _result(self, name: str, *values):
        self.calls.append((name, *values))
        return (CudaError(700 if self.fail == name else 0), *values)

    def cudaStreamCreate(self):
        return self._result("cudaStreamCreate", 77)

    def cudaMalloc(self, nbytes):
        pointer = 4096 * (len(self.memory) + 1)
        self.memory[pointer] = bytearray(nbytes)
        return self._result("cudaMalloc", pointer)

    def cudaMemcpyAsync(self, dst, src, nbytes, kind, stream):
        assert stream == 77
        if kind == "H2D":
            self.memory[dst][:nbytes] = ctypes.string_at(src, nbytes)
        else:
            ctypes.memmove(dst, bytes(self.memory[src][:nbytes]), nbytes)
        return self._result("cudaMemcpyAsync", kind)[:1]

    def cudaStreamSynchronize(self, stream):
        return self._result("cudaStreamSynchronize")[:1]


class FakeEngine:
    def __init__(self, cudart: FakeCudart, names: list[str]) -> None:
        self.cudart, self.names = cudart, names
        self.num_io_tensors = len(names)
        self.contexts: list[FakeContext] = []

    def get_tensor_name(self, i: int) -> str:
        return self.names[i]

    def get_tensor_mode(self, name: str) -> str:
        return "IN" if name in ("lnes", "window_ms", S_IN) else "OUT"

    def create_execution_context(self):
        self.contexts.append(FakeContext(self.cudart))
        return self.contexts[-1]


class FakeContext:
    def __init__(self, cudart: FakeCudart) -> None:
        self.cudart, self.shapes, self.addresses, self.runs = cudart, {}, {}, 0

    def set_input_shape(self, name, shape):
        self.shapes[name] = tuple(shape)

    def set_tensor_address(self, name, pointer):
        self.addresses[name] = pointer

    def get_tensor_shape(self, name):
        return {"pose": self.shapes["lnes"], S_OUT: self.shapes[S_IN]}[name]

    def _read(self, name):
        count = int(np.prod(self.shapes[name]))
        return np.frombuffer(bytes(self.cudart.memory[self.addresses[name]][:4 * count]), np.float32).reshape(
            self.shapes[name])

    def execute_async_v3(self, stream):
        assert stream == 77
        self.runs += 1
        out = toy_step(self._read("lnes"), self._read("window_ms"), self._read(S_IN))
        for name, value in out.items():
            self.cudart.memory[self.addresses[name]][:value.nbytes] = value.tobytes()
        return True


def fake_tensorrt(engine: FakeEngine | None, seen: list) -> types.ModuleType:
    trt = types.ModuleType("tensorrt")

    class Logger:
        WARNING = "warning"

        def __init__(self, level):
            seen.append(("logger", level))

    class Runtime:
        def __init__(self, logger):
            assert isinstance(logger, Logger)

        def deserialize_cuda_engine(self, data):
            seen.append(("engine", bytes(data)))
            return engine

    trt.Logger, trt.Runtime = Logger, Runtime
    trt.TensorIOMode = types.SimpleNamespace(INPUT="IN", OUTPUT="OUT")
    return trt


@pytest.fixture
def trt_world(monkeypatch, tmp_path):
    """(engine path, cudart, engine, seen): the fakes installed, an engine file and its sidecar written."""
    cudart = FakeCudart()
    engine = FakeEngine(cudart, ["lnes", "window_ms", S_IN, "pose", S_OUT])
    seen: list = []
    monkeypatch.setitem(sys.modules, "tensorrt", fake_tensorrt(engine, seen))
    for name, module in (("cuda", types.ModuleType("cuda")), ("cuda.bindings", types.ModuleType("cuda.bindings")),
                         ("cuda.bindings.runtime", cudart)):
        monkeypatch.setitem(sys.modules, name, module)
    path = tmp_path / "step.engine"
    path.write_bytes(b"serialized engine")
    sidecar_path(path).write_text(encode(META, {"format": "tensorrt", "precision": "fp16"}), encoding="utf-8")
    return path, cudart, engine, seen


def test_tensorrt_steps_through_device_buffers_it_allocates_once(trt_world) -> None:
    from e3dpsm.runtime.tensorrt_session import TensorRTStepSession

    path, cudart, engine, seen = trt_world
    session = TensorRTStepSession(path)
    assert seen == [("logger", "warning"), ("engine", b"serialized engine")]
    assert session.runtime == "tensorrt" and session.artifact == {"format": "tensorrt", "precision": "fp16"}
    assert (session._inputs, session._outputs) == (["lnes", "window_ms", S_IN], ["pose", S_OUT])
    rng = np.random.default_rng(0)
    state = session.init_state(1)
    for step, window in enumerate((20.0, 33.0)):
        lnes = rng.uniform(0, 1, (1, *FRAME)).astype(np.float32)
        outputs, new_state = session.step(lnes, state, window)
        expected = toy_step(lnes, window, state[STATE])
        np.testing.assert_array_equal(outputs["pose"], expected["pose"])
        np.testing.assert_array_equal(new_state[STATE], expected[S_OUT])
        assert outputs["pose"].dtype == np.float32 and outputs["pose"].shape == (1, *FRAME)
        state = new_state
    # One buffer per tensor, allocated at the first step and reused; every call checked.
    assert [c for c in cudart.calls if c[0] == "cudaMalloc"] == [
        ("cudaMalloc", 4096 * k) for k in range(1, 6)]
    assert sorted(len(b) for b in cudart.memory.values()) == sorted([4 * 32, 4, 24, 4 * 32, 24])
    copies = [c[1] for c in cudart.calls if c[0] == "cudaMemcpyAsync"]
    assert copies == ["H2D"] * 3 + ["D2H"] * 2 + ["H2D"] * 3 + ["D2H"] * 2
    assert [c[0] for c in cudart.calls][-1] == "cudaStreamSynchronize" and engine.contexts[0].runs == 2
    # Whatever a caller feeds is copied as contiguous float32, the engine's input type.
    row = session._run_one({"lnes": np.asfortranarray(np.ones((1, *FRAME))), "window_ms": np.float64([5.0]),
                            S_IN: np.zeros((1, 6), np.float16)})
    np.testing.assert_array_equal(row["pose"], np.full((1, *FRAME), 7.0, np.float32))
    np.testing.assert_array_equal(row[S_OUT], np.full((1, 6), 5.0, np.float32))


def test_tensorrt_steps_a_batch_row_by_row(trt_world) -> None:
    from e3dpsm.runtime.tensorrt_session import TensorRTStepSession

    session = TensorRTStepSession(trt_world[0])
    lnes = np.stack([np.zeros(FRAME, np.float32), np.ones(FRAME, np.float32)])
    outputs, state = session.run_feeds(session.feeds(lnes, session.init_state(2), np.float32([20.0, 30.0])))
    np.testing.assert_array_equal(outputs["pose"], np.stack([np.full(FRAME, 20.0), np.full(FRAME, 32.0)]))
    np.testing.assert_array_equal(state[STATE], [[20.0] * 6, [30.0] * 6])


@pytest.mark.parametrize("failing", ["cudaStreamCreate", "cudaMalloc", "cudaMemcpyAsync", "cudaStreamSynchronize"])
def test_a_failed_cuda_call_is_one_error_naming_it(trt_world, failing) -> None:
    from e3dpsm.runtime.tensorrt_session import TensorRTStepSession

    path, cudart, *_ = trt_world
    cudart.fail = failing
    with pytest.raises(ConfigError) as error:
        session = TensorRTStepSession(path)
        session.step(np.zeros((1, *FRAME), np.float32), session.init_state(1), 20.0)
    assert str(error.value) == "CUDA call failed: cudaErrorFake(700)"


def test_tensorrt_refusals_are_one_line(trt_world, monkeypatch) -> None:
    from e3dpsm.runtime.tensorrt_session import TensorRTStepSession, _check

    path, cudart, engine, seen = trt_world
    with pytest.raises(DataError, match=r"^model .*missing.engine does not exist$"):
        TensorRTStepSession(path.with_name("missing.engine"))
    sidecar_path(path).rename(path.with_name("elsewhere.json"))
    with pytest.raises(MetadataError) as error:
        TensorRTStepSession(path)
    assert str(error.value) == (f"{path} has no state layout: step.engine.json is not beside it (the converter "
                                "writes it; copy it with the artifact)")
    path.with_name("elsewhere.json").rename(sidecar_path(path))
    monkeypatch.setitem(sys.modules, "tensorrt", fake_tensorrt(None, seen))
    with pytest.raises(DataError) as error:
        TensorRTStepSession(path)
    assert str(error.value) == f"TensorRT cannot load {path}: built by another TensorRT version or for another GPU"
    engine.names = ["lnes", "window_ms", S_IN, "pose", "renamed"]
    monkeypatch.setitem(sys.modules, "tensorrt", fake_tensorrt(engine, seen))
    with pytest.raises(InputError, match=r"do not match its metadata"):
        TensorRTStepSession(path)
    assert _check((CudaError(0), 5)) == 5 and _check((CudaError(0), 5, 6)) == [5, 6] and _check(CudaError(0)) == []
    for module in ("tensorrt", "cuda"):
        installed = sys.modules[module]
        monkeypatch.setitem(sys.modules, module, None)
        with pytest.raises(ConfigError) as error:
            TensorRTStepSession(path)
        assert str(error.value) == f'{module} is not installed (to run TensorRT engines): pip install -e ".[tensorrt]"'
        monkeypatch.setitem(sys.modules, module, installed)


# --- Core ML --------------------------------------------------------------------------------

class FakeMLModel:
    """coremltools.models.MLModel of a package that keeps the state output once: `pose` and the
    state output are the same tensor in this toy, so it keeps `pose` (metadata output_aliases)."""
    opened: list[str] = []

    def __init__(self, path: str, metadata: dict[str, str]) -> None:
        FakeMLModel.opened.append(path)
        self.user_defined_metadata = metadata
        self.predictions = 0

    def get_spec(self):
        named = lambda *names: [types.SimpleNamespace(name=n) for n in names]  # noqa: E731
        return types.SimpleNamespace(description=types.SimpleNamespace(input=named("lnes", "window_ms", S_IN),
                                                                        output=named("pose", S_OUT)))

    def predict(self, feeds):
        self.predictions += 1
        assert set(feeds) == {"lnes", "window_ms", S_IN}
        out = toy_step(feeds["lnes"], feeds["window_ms"], feeds[S_IN])
        return {name: value.astype(np.float64) for name, value in out.items()}  # Core ML may answer in float64


@pytest.fixture
def coreml_world(monkeypatch, tmp_path):
    from e3dpsm.runtime import coreml_session

    package = tmp_path / "step.mlpackage"
    package.mkdir()
    record = {"format": "coreml", "precision": "fp16", "output_aliases": {"pose_again": "pose"}}
    metadata = {EMBEDDED_NAME: encode(META, record), "other": "x"}
    ct = types.ModuleType("coremltools")
    ct.models = types.SimpleNamespace(MLModel=lambda path: FakeMLModel(path, metadata))
    monkeypatch.setitem(sys.modules, "coremltools", ct)
    monkeypatch.setattr(coreml_session.platform, "system", lambda: "Darwin")
    FakeMLModel.opened.clear()
    return package, metadata


def test_core_ml_predicts_the_step_and_copies_the_aliased_outputs(coreml_world) -> None:
    from e3dpsm.runtime.coreml_session import CoreMLStepSession

    package, _ = coreml_world
    session = CoreMLStepSession(package, threads=4)
    assert FakeMLModel.opened == [str(package)] and session.runtime == "coreml"
    assert session._outputs == ["pose", S_OUT, "pose_again"]
    lnes = np.full((1, *FRAME), 0.5, np.float32)
    row = session._run_one({"lnes": lnes, "window_ms": np.float32([20.0]), S_IN: np.zeros((1, 6), np.float32)})
    assert set(row) == {"pose", S_OUT, "pose_again"} and all(v.dtype == np.float32 for v in row.values())
    np.testing.assert_array_equal(row["pose_again"], row["pose"])
    outputs, state = session.step(lnes, session.init_state(1), 20.0)
    np.testing.assert_array_equal(outputs["pose"], np.full((1, *FRAME), 21.0, np.float32))
    np.testing.assert_array_equal(state[STATE], np.full((1, 6), 20.0, np.float32))


def test_core_ml_refusals_are_one_line(coreml_world, monkeypatch) -> None:
    from e3dpsm.runtime import coreml_session
    from e3dpsm.runtime.coreml_session import CoreMLStepSession, coreml_unavailable_reason

    package, metadata = coreml_world
    assert coreml_unavailable_reason() is None
    with pytest.raises(DataError) as error:
        CoreMLStepSession(package.with_name("missing.mlpackage"))
    assert str(error.value) == f"model {package.with_name('missing.mlpackage')} does not exist (an .mlpackage is a folder)"
    (package.parent / "file.mlpackage").write_text("x")
    with pytest.raises(DataError, match="does not exist"):
        CoreMLStepSession(package.parent / "file.mlpackage")
    del metadata[EMBEDDED_NAME]
    with pytest.raises(MetadataError) as error:
        CoreMLStepSession(package)
    assert str(error.value) == (f"{package} carries no e3dpsm state layout (user-defined metadata 'e3dpsm'); write "
                                "it with `e3dpsm convert coreml`")
    monkeypatch.setattr(coreml_session.platform, "system", lambda: "Linux")
    FakeMLModel.opened.clear()
    with pytest.raises(ConfigError) as error:
        CoreMLStepSession(package)
    assert str(error.value) == "Core ML predicts on macOS only (this is Linux); convert here, run on a Mac"
    assert FakeMLModel.opened == []  # refused before the package is opened
    monkeypatch.setitem(sys.modules, "coremltools", None)
    with pytest.raises(ConfigError) as error:
        CoreMLStepSession(package)
    assert str(error.value) == 'coremltools is not installed (to run .mlpackage programs): pip install -e ".[coreml]"'
