"""Parity of an exported step graph with the PyTorch `step` over long rollouts.

Both sides run the same frames, each carrying its *own* states, and every output and every
state is compared at every step. Checks run in a fixed order, each with its own error type:
names, then shapes, then dtypes, then values.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable

import numpy as np

from e3dpsm.errors import E3DPSMError
from e3dpsm.export.spec import step_io_spec
from e3dpsm.export.torch_stepper import TorchStepper
from e3dpsm.models import OUTPUT_NAMES, E3DPSM
from e3dpsm.runtime.stepping import GraphStepper


class ParityError(E3DPSMError):
    """The graph and the PyTorch model disagree."""


class NameMismatchError(ParityError):
    pass


class ShapeMismatchError(ParityError):
    pass


class DtypeMismatchError(ParityError):
    pass


class ValueMismatchError(ParityError):
    pass


@dataclass(frozen=True)
class Tolerances:
    pose_atol_mm: float = 0.01  # every pose output, absolute, millimetres
    state_rtol: float = 1e-4    # every state: max |diff| / max |reference|


@dataclass
class TensorDiff:
    name: str
    kind: str  # "output" | "state"
    max_abs: float = 0.0
    max_rel: float = 0.0
    peak_step: int = -1
    reference_scale: float = 0.0
    limit: float = 0.0
    limit_kind: str = "abs"
    # How far the reference itself moved over the rollout (max over elements of max - min
    # over steps): a rollout stuck at one value proves nothing.
    reference_spread: float = 0.0
    _ref_min: np.ndarray | None = field(default=None, repr=False, compare=False)
    _ref_max: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def passed(self) -> bool:
        value = self.max_abs if self.limit_kind == "abs" else self.max_rel
        return bool(math.isfinite(value) and value <= self.limit)

    def update(self, step: int, got: np.ndarray, ref: np.ndarray) -> None:
        if not ref.size:
            return
        diff = float(np.max(np.abs(got.astype(np.float64) - ref.astype(np.float64))))
        if not math.isfinite(diff):
            diff = math.inf
        scale = float(np.max(np.abs(ref)))
        self._ref_min = ref.copy() if self._ref_min is None else np.minimum(self._ref_min, ref)
        self._ref_max = ref.copy() if self._ref_max is None else np.maximum(self._ref_max, ref)
        self.reference_spread = float(np.max(self._ref_max.astype(np.float64) - self._ref_min))
        self.reference_scale = max(self.reference_scale, scale)
        rel = diff / max(scale, 1e-6)
        if diff > self.max_abs or self.peak_step < 0:
            self.max_abs, self.peak_step = diff, step
        self.max_rel = max(self.max_rel, rel)

    def line(self) -> str:
        unit = " mm" if self.kind == "output" else ""
        verdict = "ok" if self.passed else "FAIL"
        return (f"{self.kind:6s} {self.name:22s} max|diff| {self.max_abs:10.3e}{unit:3s} rel {self.max_rel:9.2e} "
                f"at step {self.peak_step:5d}  (limit {self.limit_kind} {self.limit:.0e})  {verdict}")


@dataclass
class ParityReport:
    steps: int
    window_ms: float
    runtime: str
    tolerances: dict[str, float]
    diffs: list[TensorDiff] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return all(d.passed for d in self.diffs)

    def lines(self) -> list[str]:
        return [d.line() for d in self.diffs]

    def to_dict(self) -> dict[str, Any]:
        return {
            "steps": self.steps, "window_ms": self.window_ms, "runtime": self.runtime, "passed": self.passed,
            "tolerances": self.tolerances,
            "tensors": [{k: v for k, v in dict(asdict(d), passed=d.passed).items() if not k.startswith("_")}
                        for d in self.diffs],
        }


def _check_names(model: E3DPSM, runner: GraphStepper) -> None:
    spec = step_io_spec(model)
    if sorted(runner.input_names()) != sorted(spec.input_names):
        raise NameMismatchError(f"graph inputs {sorted(runner.input_names())} differ from the model's {sorted(spec.input_names)}")
    if sorted(runner.output_names_all()) != sorted(spec.output_names):
        raise NameMismatchError(f"graph outputs {sorted(runner.output_names_all())} differ from the model's {sorted(spec.output_names)}")
    torch_states = [s.to_metadata() for s in model.state_spec()]
    graph_states = [s.to_metadata() for s in runner.meta.states]
    if torch_states != graph_states:
        raise NameMismatchError("the graph's state metadata differs from the model's state_spec(); re-export the graph")


def _check_shapes_dtypes(name: str, got: np.ndarray, ref: np.ndarray) -> None:
    if tuple(got.shape) != tuple(ref.shape):
        raise ShapeMismatchError(f"{name}: graph gives shape {list(got.shape)}, PyTorch {list(ref.shape)}")
    if got.dtype != ref.dtype:
        raise DtypeMismatchError(f"{name}: graph gives dtype {got.dtype}, PyTorch {ref.dtype}")


def run_parity(
    model: E3DPSM, runner: GraphStepper, frames: Iterable[np.ndarray], window_ms: float,
    tolerances: Tolerances = Tolerances(), runtime: str = "onnxruntime", progress: bool = False,
) -> ParityReport:
    """Step `model` and `runner` side by side over `frames` ([2, H, W] float32 each)."""
    model = model.eval()
    _check_names(model, runner)
    specs = model.state_spec()
    diffs = {n: TensorDiff(n, "output", limit=tolerances.pose_atol_mm, limit_kind="abs") for n in OUTPUT_NAMES}
    diffs.update({s.name: TensorDiff(s.name, "state", limit=tolerances.state_rtol, limit_kind="rel") for s in specs})
    reference = TorchStepper(model)
    torch_state = reference.init_state(1)
    graph_state = runner.init_state(1)
    steps = 0
    iterator: Iterable[np.ndarray] = frames
    if progress:
        from tqdm import tqdm

        iterator = tqdm(frames, desc=f"parity {runtime} {window_ms:g} ms", unit="step", leave=False, disable=None)
    for step, frame in enumerate(iterator):
        lnes = np.ascontiguousarray(frame[None], dtype=np.float32)
        ref_out, torch_state = reference.step(lnes, torch_state, window_ms)
        got_out, graph_state = runner.step(lnes, graph_state, window_ms)
        pairs = [(n, got_out[n], ref_out[n]) for n in OUTPUT_NAMES]
        pairs += [(s.name, graph_state[s.name], torch_state[s.name]) for s in specs]
        if step == 0:
            for name, got, ref in pairs:
                _check_shapes_dtypes(name, got, ref)
        for name, got, ref in pairs:
            diffs[name].update(step, got, ref)
        steps += 1
    return ParityReport(steps, float(window_ms), runtime, asdict(tolerances), list(diffs.values()))


def assert_parity(report: ParityReport) -> None:
    if not report.passed:
        failed = [d for d in report.diffs if not d.passed]
        raise ValueMismatchError(
            f"parity failed at {report.window_ms:g} ms for {', '.join(d.name for d in failed)}: " + failed[0].line().strip()
        )
