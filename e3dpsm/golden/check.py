"""`golden check`: run a graph over a golden record's frames, carrying its own states, and
compare every output and state at every step with the record. Torch-free: this is what a
user runs on the device after copying `step.onnx` and `golden/` there.

Checks run in a fixed order: layout (variant, frame shape, output and state names and
shapes; a mismatch is bad input, exit 2), then values step by step.

An fp32 graph must reproduce the golden at the parity tolerances. A compressed graph answers
two questions, each on its own: is it within its accuracy budget (its task metrics against
the golden's fp32 poses on the golden's ground truth, e3dpsm/budget.py), and does this
device compute what the host computed for the same graph (its outputs against the host's
rollout of that graph, host.py, at a tolerance that knows the ISA). Its states must also stay
bounded. Its distance to the fp32 poses is reported, a fidelity figure, not a verdict.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from e3dpsm.errors import DataError
from e3dpsm.golden.host import HostRollout, KernelParity
from e3dpsm.golden.store import GoldenRecord
from e3dpsm.golden.tolerances import ToleranceProfile
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.metrics import joint_errors
from e3dpsm.runtime.stepping import GraphStepper

REPORT_STEPS = (1, 10, 100)  # errors reported at these steps (1-based) and at the last one
FIDELITY_MEASURE = "mean_joint_distance_mm"  # a compressed graph's outputs to the fp32 golden: reported
HOST_MEASURE = "host_distance_mm"            # ... to the host's rollout of the same graph: judged
MIN_GROWTH_STEPS = 20  # growth compares quarters of the rollout: shorter ones are not judged
TINY = 1e-12


@dataclass
class TensorCheck:
    """The error of one output or state at every step, and its verdict."""

    name: str
    kind: str  # "output" | "state"
    measure: str  # "max_abs_mm" | "mean_joint_distance_mm" | "rel_to_absmax"
    errors: np.ndarray
    step_limit: float
    mean_limit: float | None = None
    growth_limit: float | None = None
    growth_floor: float = 0.0  # a median below it counts as it (tolerances.ToleranceProfile)

    def _early(self) -> float:
        """The first quarter's median error, raised to the floor."""
        return max(float(np.median(self.errors[: len(self.errors) // 4])), self.growth_floor)

    def _late(self) -> float:
        """The last quarter's median error, raised to the floor."""
        n = len(self.errors)
        return max(float(np.median(self.errors[n - n // 4:])), self.growth_floor)

    @property
    def growth(self) -> float | None:
        """Median error over the last quarter / over the first quarter, each raised to the
        floor (None: too short)."""
        n = len(self.errors)
        if n < MIN_GROWTH_STEPS:
            return None
        early, late = self._early(), self._late()
        return late / early if early > TINY else (math.inf if late > TINY else 1.0)

    @property
    def growth_passed(self) -> bool:
        growth = self.growth
        return self.growth_limit is None or growth is None or growth <= self.growth_limit

    @property
    def first_failing_step(self) -> int | None:
        """The first step over the per-step limit; for a mean budget alone, the step from
        which the running mean stays above the budget to the end of the rollout."""
        over = np.flatnonzero(~(self.errors <= self.step_limit))  # NaN counts as over
        first = int(over[0]) if over.size else None
        if self.mean_limit is not None and not self.mean_passed:
            running = np.cumsum(self.errors) / np.arange(1, len(self.errors) + 1)
            within = np.flatnonzero(running <= self.mean_limit)
            since = int(within[-1]) + 1 if within.size else 0
            first = since if first is None else min(first, since)
        if not self.growth_passed:
            n = len(self.errors)
            bound = self.growth_limit * self._early()
            late = np.flatnonzero(self.errors[n - n // 4:] > bound)
            since = n - n // 4 + (int(late[0]) if late.size else 0)
            first = since if first is None else min(first, since)
        return first

    @property
    def mean(self) -> float:
        return float(np.mean(self.errors)) if self.errors.size else 0.0

    @property
    def mean_passed(self) -> bool:
        return self.mean_limit is None or (math.isfinite(self.mean) and self.mean <= self.mean_limit)

    @property
    def passed(self) -> bool:
        return self.first_failing_step is None

    def at_steps(self) -> dict[str, float]:
        n = len(self.errors)
        marks = sorted({s for s in (*REPORT_STEPS, n) if s <= n})
        return {str(s): float(self.errors[s - 1]) for s in marks}

    def to_dict(self) -> dict[str, Any]:
        worst = int(np.nanargmax(self.errors)) if np.isfinite(self.errors).any() else 0
        return {
            "name": self.name, "kind": self.kind, "measure": self.measure, "passed": self.passed,
            "max": float(np.max(self.errors)), "max_at_step": worst, "mean": self.mean,
            "step_limit": self.step_limit, "mean_limit": self.mean_limit,
            "first_failing_step": self.first_failing_step, "at_steps": self.at_steps(),
            "growth": self.growth, "growth_limit": self.growth_limit, "growth_floor": self.growth_floor,
        }

    def line(self) -> str:
        unit = " mm" if self.kind == "output" else "   "
        mean = f" mean {self.mean:9.3e}{unit} (limit {self.mean_limit:.2e})" if self.mean_limit is not None else ""
        if self.growth_limit is not None and self.growth is not None:
            mean += f" growth x{self.growth:.2f} (limit x{self.growth_limit:g})"
        first = self.first_failing_step
        verdict = "ok" if first is None else f"FAIL from step {first}"
        return (f"{self.kind:6s} {self.name:22s} max {float(np.max(self.errors)):9.3e}{unit} "
                f"(step limit {self.step_limit:.2e}){mean}  {verdict}")


@dataclass
class GoldenCheck:
    profile: ToleranceProfile
    scale_mm: float | None
    tensors: list[TensorCheck]
    steps: int
    seconds: float
    budget: Any = None                  # e3dpsm.budget.BudgetCheck of a compressed graph (ground truth needed)
    host: dict[str, Any] | None = None  # the host rollout the outputs were held to, if recorded

    @property
    def passed(self) -> bool:
        """Every judged tensor within its limits, and the budget not surely over. An undecided
        budget (a golden too short to bound a metric inside its limit) does not fail a device:
        the quantiser held the graph to the budget on its own held-out frames; the host
        question is what a device answers (the summary says the budget is undecided)."""
        return all(t.passed for t in self.tensors) and (self.budget is None or self.budget.answer != "over")

    @property
    def questions(self) -> dict[str, Any]:
        """A compressed graph's two answers: its budget ("within", "over", "undecided"); the
        same as the host computed."""
        host = [t for t in self.tensors if t.measure == HOST_MEASURE]
        return {"within_budget": None if self.budget is None else self.budget.answer,
                "same_as_host": all(t.passed for t in host) if host else None}

    @property
    def first_failure(self) -> dict[str, Any] | None:
        failing = [(t.first_failing_step, i, t) for i, t in enumerate(self.tensors) if not t.passed]
        if not failing:
            return None
        step, _, tensor = min(failing, key=lambda f: (f[0], f[1]))
        return {"step": step, "tensor": tensor.name, "kind": tensor.kind, "error": float(tensor.errors[step]),
                "step_limit": tensor.step_limit, "mean_limit": tensor.mean_limit, "measure": tensor.measure}

    def summary(self) -> str:
        if self.passed and self.budget is not None and self.budget.answer == "undecided":
            worst = max(self.budget.metrics, key=lambda m: m.upper_pct / m.limit_pct)
            return (f"PASSED: {self.steps} steps within the {self.profile.name} profile; budget undecided on "
                    f"{self.budget.frames} frames ({worst.name} {worst.change_pct:+.2f}%, upper bound "
                    f"{worst.upper_pct:+.2f}% over +{worst.limit_pct:g}%): record a longer golden to decide")
        if self.passed:
            return f"PASSED: {self.steps} steps within the {self.profile.name} profile"
        f = self.first_failure
        if f is None:  # every tensor within its limits: the budget failed
            worst = max(self.budget.metrics, key=lambda m: m.upper_pct / m.limit_pct)
            return (f"FAILED: over its accuracy budget, {worst.name} {worst.change_pct:+.2f}% (upper bound "
                    f"{worst.upper_pct:+.2f}%, limit +{worst.limit_pct:g}%)")
        return (f"FAILED: first at step {f['step']}, {f['kind']} {f['tensor']} "
                f"({f['measure']} {f['error']:.3e}, step limit {f['step_limit']:.2e})")

    def to_dict(self) -> dict[str, Any]:
        return {"passed": self.passed, "profile": self.profile.to_dict(), "steps": self.steps,
                "questions": self.questions, "budget": None if self.budget is None else self.budget.to_dict(),
                "host_rollout": self.host,
                "scale_mm": self.scale_mm, "first_failure": self.first_failure, "seconds": round(self.seconds, 3),
                "ms_per_step": round(1e3 * self.seconds / max(self.steps, 1), 3),
                "tensors": [t.to_dict() for t in self.tensors]}


def check_layout(golden: GoldenRecord, meta: GraphMetadata) -> None:
    """The graph must be one of the graphs the golden was recorded for (exit 2 otherwise)."""
    source_variant = golden.manifest["source"].get("variant")
    if meta.config.get("variant") != source_variant:
        raise DataError(f"the golden was recorded from variant {source_variant!r}, the graph is "
                        f"{meta.config.get('variant')!r}")
    frame = tuple(int(d) for d in meta.frame_input["shape"][1:])
    if frame != golden.frame_shape:
        raise DataError(f"the graph takes frames {list(frame)}, the golden holds {list(golden.frame_shape)}")
    if sorted(meta.output_names) != sorted(golden.output_names):
        raise DataError(f"graph outputs {sorted(meta.output_names)} differ from the golden's {sorted(golden.output_names)}")
    graph_states = {s.name: list(s.shape) for s in meta.states}
    golden_states = {s["name"]: [int(d) for d in s["shape"][1:]] for s in golden.manifest["states"]}
    if graph_states != golden_states:
        raise DataError(f"the graph's states {graph_states} differ from the golden's {golden_states}")


def _state_error(golden: GoldenRecord, name: str, step: int, state: np.ndarray, snapshot_row: int | None,
                 exact: bool) -> float:
    """fp32: max |diff| / max |golden| (the parity measure). Compressed graphs: the relative
    RMS error ||diff|| / ||golden|| over the sampled elements, over the whole state at the
    snapshot steps (one outlier element says little about a quantised state)."""
    one = state[0].reshape(-1).astype(np.float64)
    if snapshot_row is not None:
        got, ref = one, golden.snapshot(name)[snapshot_row].reshape(-1).astype(np.float64)
    else:
        got, ref = one[golden.state_index(name)], golden.state_sample(name)[step].astype(np.float64)
    if not got.size:
        return 0.0
    if exact:
        err = float(np.max(np.abs(got - ref)))
        if snapshot_row is None:  # samples: the magnitude is the whole state's
            return err / max(float(golden.state_absmax(name)[step]), TINY) if math.isfinite(err) else math.inf
        return err / max(float(np.max(np.abs(ref))), TINY) if math.isfinite(err) else math.inf
    diff, norm = float(np.linalg.norm(got - ref)), float(np.linalg.norm(ref))
    if not math.isfinite(diff):
        return math.inf
    return diff / norm if norm > TINY else (0.0 if diff <= TINY else math.inf)


def check_golden(runner: GraphStepper, golden: GoldenRecord, profile: ToleranceProfile, *,
                 progress: bool = False, host: HostRollout | None = None, budget: Any = None,
                 isa_kind: str | None = None, parity: KernelParity = KernelParity()) -> GoldenCheck:
    """Step `runner` over the golden frames with its own states; compare every step. A
    compressed graph (budget profile) is also held to `budget` (e3dpsm.budget.TaskBudget;
    None: its default) and, where `host` is given, to the host's rollout of it at `parity`'s
    tolerance for a device of `isa_kind`."""
    check_layout(golden, runner.meta)
    exact = profile.kind == "exact"
    if not exact and golden.gt_mm is None:
        raise DataError("the golden has no ground truth, so no accuracy budget for a compressed graph; "
                        "record it from prepared data or check with --profile fp32")
    outputs, state_err, seconds = _step_all(runner, golden, exact, progress, profile.name)
    tensors: list[TensorCheck] = []
    for name in golden.output_names:
        got, ref = outputs[name], golden.output(name).astype(np.float64)
        if exact:
            errors = _finite(np.max(np.abs(got - ref), axis=(1, 2)))
            tensors.append(TensorCheck(name, "output", "max_abs_mm", errors, float(profile.pose_atol_mm)))
            continue
        tensors.append(TensorCheck(name, "output", FIDELITY_MEASURE, _finite(joint_errors(got, ref).mean(axis=1)),
                                   math.inf))
        if host is not None:
            mean_limit, step_limit = parity.limits(host.same_kind(isa_kind or ""))
            errors = _finite(joint_errors(got, host.outputs[name].astype(np.float64)).mean(axis=1))
            tensors.append(TensorCheck(name, "output", HOST_MEASURE, errors, step_limit, mean_limit=mean_limit))
    for name, errors in state_err.items():
        # A compressed graph's states are not fp32's (INT8 S5 states sit ~0.5 relative RMS
        # away): how far is reported; that they stay bounded (growth) is judged.
        tensors.append(TensorCheck(name, "state", "rel_to_absmax" if exact else "rel_rms", _finite(errors),
                                   profile.state_rtol if exact else math.inf,
                                   growth_limit=None if exact else profile.max_growth,
                                   growth_floor=profile.growth_floor or 0.0))
    accuracy = None
    if not exact:
        from e3dpsm.budget import TaskBudget, check_budget

        gt = golden.gt_mm.astype(np.float64)
        accuracy = check_budget([outputs["pose"]], [golden.output("pose").astype(np.float64)], [gt],
                                budget or TaskBudget())
    scale = golden.manifest.get("mpjpe_scale_mm")
    return GoldenCheck(profile, float(scale) if scale else None, tensors, golden.steps, seconds, accuracy,
                       dict(host.entry) if host is not None else None)


def _finite(errors: np.ndarray) -> np.ndarray:
    errors = np.asarray(errors, dtype=np.float64).copy()
    errors[~np.isfinite(errors)] = math.inf
    return errors


def _step_all(runner: GraphStepper, golden: GoldenRecord, exact: bool, progress: bool,
              name: str) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
    """Every output of `runner` at every step ([N, J, 3] float64) and every state's error."""
    steps = golden.steps
    outputs = {n: np.zeros((steps, *golden.output(n).shape[1:])) for n in golden.output_names}
    state_err = {n: np.zeros(steps) for n in golden.state_names}
    snapshot_rows = {int(s): i for i, s in enumerate(golden.snapshot_steps)}
    iterator: Any = range(steps)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc=f"golden check ({name})", unit="step", leave=False, disable=None)
    started = time.perf_counter()
    state = runner.init_state(1)
    for step in iterator:
        got, state = runner.step(golden.frame(step), state, golden.window_ms(step))
        for n in golden.output_names:
            outputs[n][step] = np.asarray(got[n], dtype=np.float64)[0]
        for n in golden.state_names:
            state_err[n][step] = _state_error(golden, n, step, np.asarray(state[n]), snapshot_rows.get(step), exact)
    return outputs, state_err, time.perf_counter() - started


def plot_check(result: GoldenCheck, path: Any, title: str = "") -> None:
    """Error against step: outputs (mm) and states (relative), limits dashed, log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), constrained_layout=True)
    first = result.first_failure
    for ax, kind, unit in ((axes[0], "output", "mm"), (axes[1], "state", "relative")):
        limits = set()
        for t in (t for t in result.tensors if t.kind == kind):
            steps = np.arange(len(t.errors))
            ax.plot(steps, np.maximum(t.errors, 1e-12), lw=1.0, label=t.name if kind == "output" or not t.passed else None)
            limits.add(t.step_limit)
            if t.mean_limit is not None:
                limits.add(t.mean_limit)
        for limit in sorted(limits):
            ax.axhline(limit, color="k", ls="--", lw=0.8)
        if first and first["kind"] == kind:
            ax.axvline(first["step"], color="r", lw=0.8, label=f"first failure: {first['tensor']} @ {first['step']}")
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_ylabel(f"error ({unit})")
        ax.set_title(f"{kind}s")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.suptitle(title or f"golden check ({result.profile.name}): {'PASSED' if result.passed else 'FAILED'}")
    fig.savefig(path, dpi=110)
    plt.close(fig)
