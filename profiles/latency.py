"""Step runners per runtime and a side-by-side latency measurement.

Fairness: every runner sees the same frames in the same order with its own states carried,
at the same thread count, and the runners take turns in chunks of steps, so a burst of load
from elsewhere on a shared machine hits all of them rather than one.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Mapping, Protocol

import numpy as np

from e3dpsm.profiles.targets import Target
from e3dpsm.runtime.session import CarriedStateRunner


class StepRunner(Protocol):
    def reset(self) -> None: ...
    def step(self, lnes: np.ndarray) -> None: ...


class TorchRunner:
    """PyTorch eager `model.step`, states carried as tensors."""

    def __init__(self, model: Any, threads: int, window_ms: float) -> None:
        import torch

        torch.set_num_threads(threads)
        self.torch, self.model, self.window_ms = torch, model.eval(), window_ms
        self.reset()

    def reset(self) -> None:
        self.state = self.model.init_state(1, device="cpu")

    def step(self, lnes: np.ndarray) -> None:
        with self.torch.inference_mode():
            _, self.state = self.model.step(self.torch.from_numpy(lnes), self.state, self.window_ms)


def ort_session_options(threads: int, profile_prefix: str | None = None) -> Any:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    if profile_prefix:
        options.enable_profiling = True
        options.profile_file_prefix = profile_prefix
    return options


class OrtRunner(CarriedStateRunner):
    """An onnxruntime step graph through e3dpsm.runtime.StepSession."""

    def __init__(self, path: str, target: Target, window_ms: float, profile_prefix: str | None = None) -> None:
        from e3dpsm.runtime.session import StepSession

        providers: list[Any] = [(target.provider, dict(target.options))] if target.options else [target.provider]
        if target.provider != "CPUExecutionProvider":
            providers.append("CPUExecutionProvider")  # nodes the accelerator lacks
        super().__init__(StepSession(path, threads=target.threads, providers=providers,
                                     options=ort_session_options(target.threads, profile_prefix)), window_ms)

    def end_profiling(self) -> str:
        return self.session.session.end_profiling()


class ArtifactRunner(CarriedStateRunner):
    """An edge artifact (.pte, .tflite) through its runner (e3dpsm.runtime.stepping.open_stepper)."""

    def __init__(self, path: str, target: Target, window_ms: float) -> None:
        from e3dpsm.runtime.stepping import open_stepper

        super().__init__(open_stepper(path, threads=target.threads), window_ms)


def openvino_precision(target: Target) -> str:
    """The inference precision OpenVINO is told: bf16 for bf16 targets, f32 otherwise (no
    silent bf16 / fp16 on capable CPUs: an int8 graph's float parts stay float32, as they do
    in ONNX Runtime). fp16 targets run the fp16 graph, whose Casts decide its precision."""
    return "bf16" if target.precision == "bf16" else "f32"


LATENCY_HINT = {"PERFORMANCE_HINT": "LATENCY"}


class OpenVinoRunner:
    """OpenVINO compiled model; state outputs fed back by the names in the graph metadata."""

    def __init__(self, path: str, target: Target, window_ms: float) -> None:
        import onnx

        from e3dpsm.graph_metadata import GraphMetadata
        from e3dpsm.runtime.openvino_session import compile_config, openvino_core

        self.meta = GraphMetadata.from_onnx(onnx.load(path, load_external_data=False))
        core = openvino_core()
        config = compile_config(target.threads, LATENCY_HINT, precision=openvino_precision(target))
        self.compiled = core.compile_model(path, target.provider, config)
        self.request = self.compiled.create_infer_request()
        self.window = np.full((1,), window_ms, np.float32)
        self.reset()

    def reset(self) -> None:
        self.state = {s.input_name: s.initial_value(1) for s in self.meta.states}

    def step(self, lnes: np.ndarray) -> None:
        feeds = {self.meta.frame_input["name"]: lnes, self.meta.window_input["name"]: self.window, **self.state}
        results = self.request.infer(feeds)
        # A port can carry several names (fusion_pose_out is an Identity of pose): map them all.
        by_name = {name: value for port, value in results.items() for name in port.get_names()}
        self.state = {s.input_name: by_name[s.output_name] for s in self.meta.states}


class OpenVinoStatefulRunner:
    """The same graph converted to a stateful IR (batch 1): states stay inside the request as
    OpenVINO variables, a step feeds only the frame and the window length."""

    def __init__(self, path: str, target: Target, window_ms: float) -> None:
        import openvino as ov

        from e3dpsm.export.openvino_ir import convert_step_graph
        from e3dpsm.runtime.openvino_session import compile_config
        from e3dpsm.runtime.openvino_stateful import metadata_from_ir

        model, _ = convert_step_graph(path, stateful=True, batch=1)  # in memory; no IR file needed to time it
        meta = metadata_from_ir(model, path)
        config = compile_config(target.threads, LATENCY_HINT, precision=openvino_precision(target))
        self.request = ov.Core().compile_model(model, target.provider, config).create_infer_request()
        self.frame_name, self.window_name = meta.frame_input["name"], meta.window_input["name"]
        self.window = np.full((1,), window_ms, np.float32)

    def reset(self) -> None:
        self.request.reset_state()

    def step(self, lnes: np.ndarray) -> None:
        self.request.infer({self.frame_name: lnes, self.window_name: self.window})


def measure_side_by_side(runners: Mapping[str, StepRunner], frames: np.ndarray, steps: int, warmup: int,
                         chunk: int = 25, on_chunk: Callable[[int], None] | None = None) -> dict[str, np.ndarray]:
    """Seconds per step for every runner: `warmup` untimed steps each, then `steps` timed
    steps, in rounds of `chunk` steps per runner. Step k uses frame k (mod the frame count).
    `on_chunk(n)` is called after every n timed steps of a runner (progress bars)."""
    for runner in runners.values():
        runner.reset()
        for k in range(warmup):
            runner.step(frames[k % len(frames)][None])
    times = {name: np.empty(steps) for name in runners}
    position = {name: warmup for name in runners}
    for start in range(0, steps, chunk):
        for name, runner in runners.items():
            for k in range(start, min(start + chunk, steps)):
                frame = frames[position[name] % len(frames)][None]
                t0 = time.perf_counter()
                runner.step(frame)
                times[name][k] = time.perf_counter() - t0
                position[name] += 1
            if on_chunk is not None:
                on_chunk(min(chunk, steps - start))
    return times


def latency_summary(seconds: np.ndarray) -> dict[str, float]:
    ms = np.asarray(seconds) * 1e3
    p50, p90, p99 = np.percentile(ms, [50, 90, 99])
    return {"p50": float(p50), "p90": float(p90), "p99": float(p99), "mean": float(ms.mean()),
            "min": float(ms.min()), "steps": int(ms.size)}


def matmul_peak_gflops(threads: int, size: int = 1024, repeats: int = 20) -> dict[str, Any]:
    """The machine's practical dense float32 peak on `threads` threads, measured in the same
    run: the best size^3 matrix-product rate (2 size^3 FLOP per product) over the libraries
    present, each recorded under `by_library`.

    One library is not enough: on an AVX-512 Zen 5 host torch's BLAS measured 180 GFLOP/s
    while ONNX Runtime's MLAS reached 304 and the `paper` graph's convolutions ran above 330,
    so a torch-only "peak" made every target look closer to the ceiling than it was.
    """
    rng = np.random.default_rng(0)
    a = rng.standard_normal((size, size)).astype(np.float32)
    b = rng.standard_normal((size, size)).astype(np.float32)
    rates: dict[str, float] = {}
    for make in (_torch_matmul, _ort_matmul):  # onnxruntime is a core dependency; torch may be absent
        try:
            name, matmul = make(a, b, threads)
        except ImportError:
            continue
        matmul()
        rates[name] = 2 * size**3 / min(_timed(matmul) for _ in range(repeats)) / 1e9
    best = max(rates, key=rates.__getitem__)
    return {"gflops": rates[best], "library": best, "by_library": rates, "size": size, "threads": threads}


def _torch_matmul(a: np.ndarray, b: np.ndarray, threads: int) -> tuple[str, Callable[[], Any]]:
    import torch

    torch.set_num_threads(threads)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    return f"torch {torch.__version__}", lambda: torch.mm(ta, tb)


def _ort_matmul(a: np.ndarray, b: np.ndarray, threads: int) -> tuple[str, Callable[[], Any]]:
    import onnxruntime as ort
    from onnx import TensorProto, helper

    def tensor(name: str) -> Any:
        return helper.make_tensor_value_info(name, TensorProto.FLOAT, list(a.shape))

    graph = helper.make_graph([helper.make_node("MatMul", ["a", "b"], ["c"])], "matmul",
                              [tensor("a"), tensor("b")], [tensor("c")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    session = ort.InferenceSession(model.SerializeToString(), ort_session_options(threads),
                                   providers=["CPUExecutionProvider"])
    return f"onnxruntime {ort.__version__}", lambda: session.run(None, {"a": a, "b": b})


def _timed(fn: Callable[[], Any]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0
