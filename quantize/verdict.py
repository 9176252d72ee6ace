"""Pass 6, the verdict: is the graph within budget, and is it faster than fp32 here?

The artifact is timed beside the fp32 graph (profiles/step_timing.py: interleaved rounds, a bootstrap
interval of the speed-up) on each runtime it was checked on. The first line of report.md
says what to do with the graph: ship it for speed, ship it for size and integer-only
accelerators while naming what is faster on this host, or do not ship it (over budget).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Mapping

from e3dpsm.budget import BudgetCheck

RUNTIME_NAMES = {"onnxruntime": "ONNX Runtime", "openvino": "OpenVINO"}


# What a graph that is not faster here still serves, by mode.
ACCELERATORS = {"int8": "integer-only accelerators", "int8-dynamic": "integer-only accelerators",
                "fp16": "fp16 accelerators (GPUs, NPUs)",
                "int8-weights": "ARM and other CPUs alike (float arithmetic: the host's poses on any ISA)"}


# What to try when a graph of this mode is over budget.
OVER_BUDGET_FIX = {"int8": "keep more nodes float (`--exclude`) or calibrate on more frames.",
                   "int8-weights": "its weights alone cost too much accuracy: fine-tune for quantisation "
                                   "(`e3dpsm distill --qat`) or ship the fp32 graph."}


@dataclass(frozen=True)
class Verdict:
    mode: str
    check: BudgetCheck                       # the final check, worst runtime
    check_runtime: str
    size_ratio: float
    timings: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)  # runtime -> profiles.step_timing.time_beside
    isa: Mapping[str, Any] = field(default_factory=dict)                     # utils.isa.CpuIsa.to_dict()

    @property
    def within(self) -> bool:
        return self.check.within

    @property
    def fastest(self) -> tuple[str, float] | None:
        """(runtime, speed-up over its own fp32) of the best timed runtime."""
        timed = [(r, float(t["speedup_vs_fp32"])) for r, t in self.timings.items() if t.get("speedup_vs_fp32")]
        return max(timed, key=lambda item: item[1]) if timed else None

    def surely_faster(self, runtime: str) -> bool:
        """The whole interval above 1x, timed on a host that was not oversubscribed (a load
        burst on a shared host once timed an INT8 graph 1.63x fp32 that ran 0.93x quietly)."""
        interval = self.timings.get(runtime, {}).get("interval") or {}
        return bool(interval and interval.get("low", 0.0) > 1.0 and not self.loaded(runtime))

    def loaded(self, runtime: str) -> bool:
        load = self.timings.get(runtime, {}).get("timer", {}).get("load_average")
        return load is not None and load > (os.cpu_count() or 1)

    def headline(self) -> str:
        """report.md's first line."""
        host = f"this {self.isa.get('kind', 'unknown')} host"
        if not self.within:
            worst = max(self.check.metrics, key=lambda m: m.upper_pct / m.limit_pct)
            return (f"Verdict: over budget, do not ship: {worst.name} {worst.change_pct:+.2f}% (upper bound "
                    f"{worst.upper_pct:+.2f}%, limit +{worst.limit_pct:g}%) on {self.check.frames} held-out frames "
                    f"({RUNTIME_NAMES.get(self.check_runtime, self.check_runtime)}); {OVER_BUDGET_FIX.get(self.mode, OVER_BUDGET_FIX['int8'])}")
        budget = f"within budget on {self.check.frames} held-out frames, {self.size_ratio:.2f}x fp32's size"
        best = self.fastest
        if best is not None and self.surely_faster(best[0]):
            return (f"Verdict: ship it: {self.mode} {budget}, {best[1]:.2f}x fp32's speed on "
                    f"{RUNTIME_NAMES.get(best[0], best[0])} on {host}.")
        speeds = ", ".join(f"{RUNTIME_NAMES.get(r, r)} {float(t['speedup_vs_fp32']):.2f}x"
                           for r, t in self.timings.items() if t.get("speedup_vs_fp32"))
        if best is not None and self.loaded(best[0]):
            host += " (loaded while timed: time it again on a quiet host)"
        return (f"Verdict: no {self.mode} graph beats fp32 on {host}" + (f" ({speeds} fp32's speed)" if speeds else "")
                + f"; this one is {budget}: ship it for size and {ACCELERATORS.get(self.mode, 'accelerators')}. "
                + "Faster here: "
                + ", ".join(self.faster_alternatives()) + ".")

    def faster_alternatives(self) -> list[str]:
        """What pays for speed on a CPU where INT8 does not (docs/compress.md, docs/runtimes.md)."""
        options = ["structured pruning (`e3dpsm prune`: 3.2x on `small`)",
                   "OpenVINO with the states inside the IR (`convert openvino --stateful`, fp32)"]
        if self.isa.get("bf16"):
            options.insert(1, "bf16 on this CPU's bf16 units (profile target openvino-cpu-bf16)")
        return options

    def to_dict(self) -> dict[str, Any]:
        best = self.fastest
        return {"headline": self.headline(), "within_budget": self.within, "check_runtime": self.check_runtime,
                "size_ratio": self.size_ratio, "timings": {r: dict(t) for r, t in self.timings.items()},
                "fastest": {"runtime": best[0], "speedup_vs_fp32": best[1]} if best else None,
                "surely_faster": bool(best and self.surely_faster(best[0]))}


def time_beside_fp32(graph: Any, fp32: Any, frames: Any, window_ms: float, runtimes: tuple[str, ...],
                     threads: int | None, steps: int) -> dict[str, dict[str, Any]]:
    """The graph against fp32, side by side on the same frames with states carried, on each
    runtime (profiles.step_timing.time_beside)."""
    import numpy as np

    from e3dpsm.profiles.step_timing import time_beside
    from e3dpsm.quantize.holdout import open_stepper
    from e3dpsm.runtime.session import CarriedStateRunner

    timings = {}
    for runtime in runtimes:
        candidate, reference = (CarriedStateRunner(open_stepper(path, runtime, threads), window_ms)
                                for path in (graph, fp32))
        timed = time_beside(candidate, reference, np.asarray(frames, dtype=np.float32), steps)
        # The load average beside the timing: interleaving evens out load, a burst can still tip a ratio.
        timings[runtime] = {**timed, "timer": {**timed["timer"], "runtime": runtime, "threads": threads,
                                               "load_average": round(os.getloadavg()[0], 2)}}
    return timings
