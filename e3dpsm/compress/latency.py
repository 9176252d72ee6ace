"""The latency model pruning plans with: per-unit step time measured on the deployed graph.

`profile_units` runs the exported step graph (batch 1, states carried) under ONNX Runtime's
profiler and attributes every node's kernel time to the prunable unit (compress/units.py)
whose module path names it (`/stages.0/block1/conv1/Conv` -> `stages.0.block1`). The rest
of the step, kernels of no unit plus the runtime's per-node dispatch (the run time minus
the kernel sum, spread evenly over the nodes), is fixed.

`predict_ms` then predicts a plan's step:

    predicted = run_ms - sum over units of saved(unit)
    saved = kernel_ms(unit) + nodes(unit) * dispatch_ms_per_node      if the unit is removed
          = kernel_ms(unit) * (1 - new_width / old_width)            if it is narrowed

i.e. a unit's kernels scale linearly with its width and its nodes' dispatch does not; only
removal saves dispatch. On small CPU graphs dispatch and small ops dominate, so narrowing
buys less than its MACs suggest: measured per round against the prediction (report).
A model, not a measurement: `--target-latency-ms` is checked on the exported graph, timed.
"""
from __future__ import annotations

import json
import os
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from e3dpsm.compress.units import RES, Unit

_KERNEL_SUFFIX = "_kernel_time"


@dataclass(frozen=True)
class UnitLatency:
    kernel_ms: float
    nodes: int


@dataclass(frozen=True)
class LatencyProfile:
    """One graph's measured step: median run time, kernel time and node count per step, and
    the per-unit share of the kernels and nodes."""

    run_ms: float
    kernel_ms: float
    nodes: int
    units: Mapping[str, UnitLatency] = field(default_factory=dict)

    @property
    def dispatch_ms_per_node(self) -> float:
        return max(self.run_ms - self.kernel_ms, 0.0) / max(self.nodes, 1)

    def to_dict(self) -> dict[str, Any]:
        return {"run_ms": self.run_ms, "kernel_ms": self.kernel_ms, "nodes": self.nodes,
                "dispatch_ms_per_node": self.dispatch_ms_per_node,
                "units": {k: asdict(v) for k, v in self.units.items()}}

    def scaled(self, run_ms: float) -> "LatencyProfile":
        """The same shares on a runtime whose step measured `run_ms` (OpenVINO: its nodes are
        not ONNX nodes, so ONNX Runtime's profile lends the shares)."""
        f = run_ms / self.run_ms if self.run_ms > 0 else 1.0
        return LatencyProfile(run_ms, self.kernel_ms * f, self.nodes,
                              {k: UnitLatency(v.kernel_ms * f, v.nodes) for k, v in self.units.items()})


def unit_of_node(node: str, units: Sequence[Unit]) -> str | None:
    """The unit a graph node's work belongs to: the most specific scope that prefixes its
    name. A residual block's shortcut stays when its branch goes, so it belongs to none."""
    best: Unit | None = None
    best_len = -1
    for unit in units:
        for scope in unit.scopes:
            if node.startswith(scope) and len(scope) > best_len:
                best, best_len = unit, len(scope)
    if best is not None and best.kind == RES and node.startswith(f"{best.scope}shortcut/"):
        return None
    return best.name if best else None


def summarize_profile(events: Sequence[Mapping[str, Any]], units: Sequence[Unit]) -> LatencyProfile:
    """A LatencyProfile from ONNX Runtime trace events (its profiling JSON)."""
    runs = [float(e.get("dur", 0)) / 1e3 for e in events if e.get("cat") == "Session" and e.get("name") == "model_run"]
    steps = max(len(runs), 1)
    kernel, nodes = 0.0, 0
    per_unit: dict[str, list[float]] = {}
    for event in events:
        name = str(event.get("name", ""))
        if event.get("cat") != "Node" or not name.endswith(_KERNEL_SUFFIX):
            continue
        ms = float(event.get("dur", 0)) / 1e3
        kernel += ms
        nodes += 1
        unit = unit_of_node(name[: -len(_KERNEL_SUFFIX)], units)
        if unit is not None:
            acc = per_unit.setdefault(unit, [0.0, 0])
            acc[0] += ms
            acc[1] += 1
    return LatencyProfile(
        run_ms=float(np.median(runs)) if runs else kernel / steps, kernel_ms=kernel / steps, nodes=round(nodes / steps),
        units={k: UnitLatency(v[0] / steps, round(v[1] / steps)) for k, v in per_unit.items()},
    )


def profile_units(graph: str | os.PathLike, units: Sequence[Unit], frames: np.ndarray, window_ms: float,
                  threads: int, steps: int = 60, warmup: int = 10) -> LatencyProfile:
    """Profile `steps` carried-state steps of an fp32 step graph on ONNX Runtime's CPU."""
    from e3dpsm.profiles.latency import ort_session_options
    from e3dpsm.runtime.session import CarriedStateRunner, StepSession

    with tempfile.TemporaryDirectory(prefix="e3dpsm-prune-prof-") as tmp:
        warm = CarriedStateRunner(StepSession(graph, threads=threads), window_ms)
        for k in range(warmup):
            warm.step(frames[k % len(frames)][None])
        session = StepSession(graph, threads=threads, options=ort_session_options(threads, str(Path(tmp) / "prof")))
        runner = CarriedStateRunner(session, window_ms)
        for k in range(warmup + steps):
            runner.step(frames[k % len(frames)][None])
        trace = session.session.end_profiling()
        events = json.loads(Path(trace).read_text(encoding="utf-8"))
    # The warm-up steps of the profiled session are in the trace too: drop them.
    run_events = [e for e in events if e.get("cat") == "Session" and e.get("name") == "model_run"]
    if len(run_events) > warmup:
        cut = run_events[warmup]["ts"]
        events = [e for e in events if e.get("ts", 0) >= cut]
    return summarize_profile(events, units)


def saved_ms(profile: LatencyProfile, unit: str, old_width: int, new_width: int, removed: bool) -> float:
    """The step time a unit's cut saves, by the model of the module docstring."""
    share = profile.units.get(unit)
    if share is None or old_width <= 0:
        return 0.0
    if removed:
        return share.kernel_ms + share.nodes * profile.dispatch_ms_per_node
    return share.kernel_ms * (1.0 - new_width / old_width)


def predict_ms(profile: LatencyProfile, units: Sequence[Unit], new_widths: Mapping[str, int]) -> float:
    """Predicted step (ms) after giving the named units new widths (0 or a removed attention
    block: the unit goes; its nested units go with it)."""
    removed_scopes = [u.scope for u in units if u.name in new_widths and new_widths[u.name] == 0]
    total = 0.0
    for unit in units:
        if unit.name not in new_widths and not any(unit.scope.startswith(s) for s in removed_scopes):
            continue
        inside_removed = any(unit.scope.startswith(s) and unit.scope != s for s in removed_scopes)
        width = 0 if inside_removed else new_widths[unit.name]
        total += saved_ms(profile, unit.name, unit.width, width, removed=width == 0)
    return profile.run_ms - total
