"""Step runners per runtime and a side-by-side latency measurement.

Fairness: every runner sees the same frames in the same order with its own states carried,
at the same thread count, and the runners take turns in chunks of steps, so a burst of load
from elsewhere on a shared machine hits all of them rather than one
(`profiles.step_timing`). The runners here split a step into its phases (`prepare`, `run`:
the runtime's call alone, `collect`), so the profile reports the Python overhead apart.
"""
from __future__ import annotations

import time
from typing import Any, Callable, Mapping

import numpy as np

from e3dpsm.profiles.step_timing import StepRunner, time_side_by_side
from e3dpsm.profiles.targets import Target
from e3dpsm.runtime.session import CarriedStateRunner
from e3dpsm.utils.stats import percentiles


class TorchRunner:
    """PyTorch eager `model.step`, states carried as tensors (no copies to hand over)."""

    def __init__(self, model: Any, threads: int, window_ms: float) -> None:
        import torch

        torch.set_num_threads(threads)
        self.torch, self.model, self.window_ms = torch, model.eval(), window_ms
        self.reset()

    def reset(self) -> None:
        self.state = self.model.init_state(1, device="cpu")

    def prepare(self, lnes: np.ndarray) -> None:
        self._lnes = self.torch.from_numpy(lnes)

    def run(self) -> None:
        with self.torch.inference_mode():
            _, self.state = self.model.step(self._lnes, self.state, self.window_ms)

    def collect(self) -> None:
        pass

    def step(self, lnes: np.ndarray) -> None:
        self.prepare(lnes)
        self.run()


def ort_session_options(threads: int, profile_prefix: str | None = None, stop_spinning: bool = False) -> Any:
    """`stop_spinning`: ONNX Runtime's intra-op threads stop spinning when a run ends
    (`session.force_spinning_stop`). By default they spin on after each run (tens of ms), and
    in a side-by-side measurement that steals a core from the next runtime's first steps:
    measured on `paper` on a loaded 2-core host, OpenVINO's first step after an ONNX Runtime
    turn took 166 ms with spinning against 63 ms without (steady state ~100 ms)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    if stop_spinning:
        options.add_session_config_entry("session.force_spinning_stop", "1")
    if profile_prefix:
        options.enable_profiling = True
        options.profile_file_prefix = profile_prefix
    return options


class _SessionPhases(CarriedStateRunner):
    """A step session's `feeds` / `run_raw` / `collect` as the runner phases."""

    def prepare(self, lnes: np.ndarray) -> None:
        self._feeds = self.session.feeds(lnes, self.state, self.window_ms)

    def run(self) -> None:
        self._raw = self.session.run_raw(self._feeds)

    def collect(self) -> None:
        _, self.state = self.session.collect(self._raw)


class OrtRunner(_SessionPhases):
    """An onnxruntime step graph through e3dpsm.runtime.StepSession. `side_by_side`: its
    threads stop spinning between runs (`ort_session_options`), as the profile measures."""

    def __init__(self, path: str, target: Target, window_ms: float, profile_prefix: str | None = None,
                 side_by_side: bool = False) -> None:
        from e3dpsm.runtime.session import StepSession

        providers: list[Any] = [(target.provider, dict(target.options))] if target.options else [target.provider]
        if target.provider != "CPUExecutionProvider":
            providers.append("CPUExecutionProvider")  # nodes the accelerator lacks
        options = ort_session_options(target.threads, profile_prefix, stop_spinning=side_by_side)
        super().__init__(StepSession(path, threads=target.threads, providers=providers, options=options), window_ms)

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


def openvino_target_config(target: Target) -> dict[str, Any]:
    """Every property the profile compiles an OpenVINO target with (the outside tool is
    given the same: profiles.outside)."""
    from e3dpsm.runtime.openvino_session import compile_config

    return compile_config(target.threads, LATENCY_HINT, precision=openvino_precision(target))


class OpenVinoRunner(_SessionPhases):
    """The explicit-state graph through e3dpsm.runtime.OpenVINOStepSession: states fed in and
    read back by the names in the graph metadata."""

    def __init__(self, path: str, target: Target, window_ms: float) -> None:
        from e3dpsm.runtime.openvino_session import OpenVINOStepSession

        session = OpenVINOStepSession(path, threads=target.threads, device=target.provider,
                                      precision=openvino_precision(target), config=LATENCY_HINT)
        super().__init__(session, window_ms)

    @property
    def compiled(self) -> Any:
        return self.session.compiled


class OpenVinoStatefulRunner:
    """The same graph converted to a stateful IR (batch 1): states stay inside the request as
    OpenVINO variables, a step feeds only the frame and the window length and copies the
    pose outputs out."""

    def __init__(self, path: str, target: Target, window_ms: float) -> None:
        import openvino as ov

        from e3dpsm.export.openvino_ir import convert_step_graph
        from e3dpsm.runtime.openvino_stateful import metadata_from_ir

        model, _ = convert_step_graph(path, stateful=True, batch=1)  # in memory; no IR file needed to time it
        meta = metadata_from_ir(model, path)
        self.compiled = compiled = ov.Core().compile_model(model, target.provider, openvino_target_config(target))
        self.request = compiled.create_infer_request()
        self.frame_port = compiled.input(meta.frame_input["name"])
        self.window_port = compiled.input(meta.window_input["name"])
        self.pose_ports = [compiled.output(name) for name in meta.output_names]
        self.window = ov.Tensor(np.full((1,), window_ms, np.float32))
        self._tensor = lambda array: ov.Tensor(np.ascontiguousarray(array), shared_memory=True)

    def reset(self) -> None:
        self.request.reset_state()

    def prepare(self, lnes: np.ndarray) -> None:
        self.request.set_tensor(self.frame_port, self._tensor(lnes))
        self.request.set_tensor(self.window_port, self.window)

    def run(self) -> None:
        self.request.infer()

    def collect(self) -> None:
        self.poses = [self.request.get_tensor(port).data.copy() for port in self.pose_ports]

    def step(self, lnes: np.ndarray) -> None:
        self.prepare(lnes)
        self.run()
        self.collect()


def measure_side_by_side(runners: Mapping[str, StepRunner], frames: np.ndarray, steps: int, warmup: int,
                         chunk: int = 25, on_chunk: Callable[[int], None] | None = None) -> dict[str, np.ndarray]:
    """Seconds per whole step for every runner (`profiles.step_timing.time_side_by_side`,
    which also times the phases apart): `warmup` untimed steps each, then `steps` timed
    steps, in rounds of `chunk` steps per runner. Step k uses frame k (mod the frame count)."""
    times = time_side_by_side(runners, frames, steps, warmup, chunk, on_chunk)
    return {name: t.total for name, t in times.items()}


def latency_summary(seconds: np.ndarray) -> dict[str, float]:
    """Milliseconds per step: the shared percentiles (unrounded), the mean and the minimum."""
    ms = np.asarray(seconds, dtype=np.float64) * 1e3
    return {**percentiles(ms, digits=None), "mean": float(ms.mean()), "min": float(ms.min()), "steps": int(ms.size)}


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
