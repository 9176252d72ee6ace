"""`e3dpsm profile` without the argument parsing: counts, memory, side-by-side latency (the
runtime's call and the Python around it apart), each CPU target's outside timer, onnxruntime
op profiles, device estimates and the verdict for a list of targets, as one report body."""
from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import onnx

from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.profiles import devices as devices_mod
from e3dpsm.profiles.flops import CATEGORIES, relative_difference
from e3dpsm.profiles.flops_onnx import activation_bytes, count_onnx, initializer_values, load_graph, static_shapes
from e3dpsm.profiles.graph_groups import assign_groups
from e3dpsm.profiles.inputs import Frames
from e3dpsm.profiles.agreement import DEFAULT_TURNS, NO_AGREEMENT, ProfiledOrtRuns, measure_agreement
from e3dpsm.profiles.latency import (ArtifactRunner, OpenVinoRunner, OpenVinoStatefulRunner, OrtRunner, TorchRunner,
                                     latency_summary, matmul_peak_gflops)
from e3dpsm.profiles.memory import RssSampler
from e3dpsm.profiles.step_timing import StepTimes, time_side_by_side, turn_paired_speedup
from e3dpsm.profiles.targets import EDGE_RUNTIMES, Target, availability
from e3dpsm.profiles.verdict import fastest_path
from e3dpsm.utils.cpu_time import CpuShareMeter

BASELINES = ("torch-eager-cpu", "ort-cpu-fp32")
MEMORY_STEPS = 5


@dataclass(frozen=True)
class ProfileSettings:
    steps: int = 300
    warmup: int = 20
    chunk: int = 25
    ort_profile_steps: int = 50
    roofline_precisions: tuple[str, ...] = ("fp32", "fp16")
    outside_seconds: float = 5.0  # each CPU target's outside timer (benchmark_app ...); 0: none
    outside_turns: int = DEFAULT_TURNS  # the outside timer and the target's runner take turns


def count_both(model: Any, graph: onnx.ModelProto) -> dict[str, Any]:
    """PyTorch and ONNX counts of one pose update and how far apart their MACs are."""
    onnx_count = count_onnx(graph)
    counting: dict[str, Any] = {"onnx": onnx_count.to_dict(), "pytorch": None, "relative_difference": None}
    if model is not None:
        from e3dpsm.profiles.flops_torch import count_torch

        torch_count = count_torch(model)
        counting["pytorch"] = torch_count.to_dict()
        counting["relative_difference"] = relative_difference(torch_count.macs, onnx_count.macs)
    return counting


def build_runner(target: Target, graphs: Mapping[str, Path | None], model: Any, window_ms: float) -> Any:
    if target.runtime == "torch":
        return TorchRunner(model, target.threads, window_ms)
    path = str(graphs[target.graph_key])
    if target.runtime in EDGE_RUNTIMES:
        return ArtifactRunner(path, target, window_ms)
    if target.runtime == "onnxruntime":
        return OrtRunner(path, target, window_ms, side_by_side=True)
    if target.runtime == "openvino-stateful":
        return OpenVinoStatefulRunner(path, target, window_ms)
    return OpenVinoRunner(path, target, window_ms)


def _model_bytes(target: Target, graphs: Mapping[str, Path | None], model: Any, checkpoint: str | None) -> int:
    if target.graph != "none":
        return Path(graphs[target.graph_key]).stat().st_size
    if checkpoint:
        return Path(checkpoint).stat().st_size
    return sum(t.numel() * t.element_size() for t in model.state_dict().values())


def _ratios(entries: Sequence[Mapping[str, Any]], times: Mapping[str, StepTimes], chunk: int) -> dict[str, float]:
    """Speed-up of each target over each baseline measured in the same run, round by round
    (step_timing.turn_paired_speedup; a baseline is compared only with the targets listed
    after it in BASELINES, and with all others)."""
    measured = [e["name"] for e in entries if e.get("latency_ms") and e["name"] in times]
    ratios = {}
    for i, base in enumerate(BASELINES):
        for name in measured:
            if base in measured and name != base and name not in BASELINES[:i]:
                ratios[f"{name} vs {base}"] = turn_paired_speedup(times[name].total, times[base].total, chunk)
    return ratios


def _ort_profile(target: Target, graphs: Mapping[str, Path | None], frames: Frames, steps: int) -> dict[str, Any]:
    """A separate profiled session (profiling slows every run, so never the timed one)."""
    graph_path = Path(graphs[target.graph_key])
    graph = load_graph(graph_path)
    _, dtypes = static_shapes(graph)
    node_groups = assign_groups(graph, dtypes)
    with tempfile.TemporaryDirectory(prefix="e3dpsm-ortprof-") as tmp:
        profiled = ProfiledOrtRuns(graph_path, target, frames, steps, Path(tmp))
        profiled.turn(0)
        return profiled.summary(node_groups)


def _target_entry(target: Target, graphs: Mapping[str, Path | None], model: Any, params: int,
                  primary: Mapping[str, Any]) -> dict[str, Any]:
    status = availability(target, graphs, model is not None)
    return {**target.to_dict(), "available": status.available, "reason": status.reason, "params": params,
            "macs": primary["macs"], "flops": primary["flops"], "latency_ms": None, "runtime_ms": None,
            "overhead_ms": None, "hz": None, "peak_rss_mb": None, "model_bytes": None, "outside": None,
            **NO_AGREEMENT}


def _load_runners(targets: Sequence[Target], entries: Sequence[dict[str, Any]], graphs: Mapping[str, Path | None],
                  model: Any, frames: Frames, checkpoint: str | None) -> dict[str, Any]:
    """A runner per available target (its load and first steps sampled for memory); a
    runtime that refuses the graph turns its entry unavailable, with the reason."""
    runners: dict[str, Any] = {}
    for target, entry in zip(targets, entries):
        if not entry["available"]:
            continue
        try:
            with RssSampler() as rss:
                runner = build_runner(target, graphs, model, frames.window_ms)
                for k in range(MEMORY_STEPS):
                    runner.step(frames.lnes[k % len(frames.lnes)][None])
        except Exception as exc:  # a runtime that refuses the graph is a result, not a crash
            entry.update(available=False, reason=f"failed to load or run: {str(exc).splitlines()[0][:300]}")
        else:
            runners[target.name] = runner
            entry.update(peak_rss_mb=rss.peak_mb, rss_growth_mb=rss.growth_mb,
                         model_bytes=_model_bytes(target, graphs, model, checkpoint))
    return runners


def _record_times(entry: dict[str, Any], times: StepTimes, peak_gflops: float) -> None:
    summary = latency_summary(times.total)
    entry.update(latency_ms=summary, hz=1e3 / summary["p50"])
    if times.runtime is not None:
        entry.update(runtime_ms=latency_summary(times.runtime), overhead_ms=latency_summary(times.overhead))
    entry["gflops_achieved"] = entry["flops"] / (summary["p50"] / 1e3) / 1e9
    entry["peak_fraction"] = entry["gflops_achieved"] / peak_gflops


def _outside_figures(targets: Sequence[Target], entries: Sequence[dict[str, Any]], runners: Mapping[str, Any],
                     graphs: Mapping[str, Path | None], frames: Frames, settings: ProfileSettings) -> None:
    """Each measured target's outside timer, timed in turns with the target's own runner
    (profiles.agreement), beside the profile's runtime figure."""
    for target, entry in zip(targets, entries):
        if entry["latency_ms"] is None:
            continue
        graph = graphs.get(target.graph_key) if target.graph != "none" else None
        entry.update(measure_agreement(runners[target.name], target, graph, frames, settings.outside_seconds,
                                       settings.ort_profile_steps, settings.chunk, settings.outside_turns))


def profile_targets(
    targets: Sequence[Target], graphs: Mapping[str, Path | None], model: Any, frames: Frames,
    settings: ProfileSettings, checkpoint: str | None = None, progress: bool = False,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The report body (without the header) and the per-target step times (seconds)."""
    graph = load_graph(graphs["fp32"])
    meta = GraphMetadata.from_onnx(graph)
    counting = count_both(model, graph)
    primary = counting["pytorch"] or counting["onnx"]
    params = primary["params"] if primary["params"] is not None else initializer_values(graph)

    entries = [_target_entry(target, graphs, model, params, primary) for target in targets]
    runners = _load_runners(targets, entries, graphs, model, frames, checkpoint)

    from tqdm import tqdm

    threads = targets[0].threads if targets else 1
    # The peak is measured before and after the timed steps and the better kept: on a shared
    # host a burst of outside load during one measurement halved it (152 vs 305 GFLOP/s).
    peak_before = matmul_peak_gflops(threads)
    with RssSampler() as overall, CpuShareMeter() as timed_cpu, \
            tqdm(total=settings.steps * len(runners), desc="timed steps", unit="step", disable=not progress) as bar:
        times = time_side_by_side(runners, frames.lnes, settings.steps, settings.warmup, settings.chunk,
                                  on_chunk=bar.update)
    peak_after = matmul_peak_gflops(threads)
    peak = {**max(peak_before, peak_after, key=lambda p: p["gflops"]),
            "measured_gflops": [peak_before["gflops"], peak_after["gflops"]]}
    for entry in entries:
        if entry["name"] in times:
            _record_times(entry, times[entry["name"]], peak["gflops"])

    ort_profiles = {}
    for target in targets:
        if target.name in runners and target.runtime == "onnxruntime" and settings.ort_profile_steps > 0:
            ort_profiles[target.name] = _ort_profile(target, graphs, frames, settings.ort_profile_steps)
    with CpuShareMeter() as outside_cpu:
        if settings.outside_seconds > 0:
            _outside_figures(targets, entries, runners, graphs, frames, settings)

    state_values = sum(math.prod(s.shape) for s in meta.states)
    act_values = activation_bytes(graph) // 4
    rooflines = [
        devices_mod.roofline(device, primary["flops"],
                             devices_mod.bytes_per_step(params, act_values, state_values, precision), precision)
        for device in devices_mod.load_devices() for precision in settings.roofline_precisions
    ]
    body = {
        "counting": {**counting, "categories": list(CATEGORIES)},
        "verdict": fastest_path(entries), "targets": entries, "ratios": _ratios(entries, times, settings.chunk),
        "machine_peak": peak, "process_peak_rss_mb": overall.peak_mb,
        "cpu_time": {"timed_steps": timed_cpu.shares, "outside_timers": outside_cpu.shares},
        "ort_profiles": ort_profiles, "devices": rooflines,
        "bytes_per_step_inputs": {"weight_values": params, "activation_values": act_values,
                                  "state_values": state_values},
    }
    return body, {name: t.total for name, t in times.items()}
