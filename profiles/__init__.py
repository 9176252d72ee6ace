"""Profiling of E-3DPSM across deployment targets: MACs per module (PyTorch and ONNX
counters, one convention), memory, side-by-side latency, and device roofline estimates.

    e3dpsm.profiles.flops          convention, module groups, shared formulas, paper table
    e3dpsm.profiles.flops_torch    count_torch(model) -> FlopCount          (imports torch)
    e3dpsm.profiles.flops_onnx     count_onnx(graph or path) -> FlopCount   (torch-free)
    e3dpsm.profiles.graph_groups   ONNX node -> module group
    e3dpsm.profiles.targets        targets.toml: load_targets, select_targets, availability
    e3dpsm.profiles.devices        devices.toml: load_devices, roofline
    e3dpsm.profiles.latency        runners per runtime (phased steps), measure_side_by_side, matmul peak
    e3dpsm.profiles.step_timing    time_side_by_side: whole step and the runtime's call, apart
    e3dpsm.profiles.memory         RssSampler
    e3dpsm.profiles.inputs         synthetic or prepared LNES frames
    e3dpsm.profiles.ort_profile    onnxruntime profiling trace -> ms per op type / module
    e3dpsm.profiles.outside        the runtimes' own timers: benchmark_app, onnxruntime_perf_test, ORT profiler
    e3dpsm.profiles.agreement      each target's outside figure on the graph and settings it was timed with
    e3dpsm.profiles.verdict        the fastest path on this host, ties named
    e3dpsm.profiles.graphs         the graphs a profile runs (the static-batch export, parity-checked)
    e3dpsm.profiles.profiler       profile_targets: measurements of `e3dpsm profile` as one report body
    e3dpsm.profiles.command        the bodies of `e3dpsm profile` and `e3dpsm model-info` (reports written)
    e3dpsm.profiles.report         report.md and plots
"""
from e3dpsm.profiles.devices import Device, load_devices, roofline
from e3dpsm.profiles.flops import MODULE_GROUPS, PAPER_EFFICIENCY, FlopCount, ModuleCount
from e3dpsm.profiles.targets import Availability, Target, availability, load_targets, select_targets

__all__ = [
    "Availability", "Device", "FlopCount", "MODULE_GROUPS", "ModuleCount", "PAPER_EFFICIENCY", "Target",
    "availability", "load_devices", "load_targets", "roofline", "select_targets",
]
