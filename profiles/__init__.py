"""Profiling of E-3DPSM across deployment targets: MACs per module (PyTorch and ONNX
counters, one convention), memory, side-by-side latency, and device roofline estimates.

    e3dpsm.profiles.flops          convention, module groups, shared formulas, paper table
    e3dpsm.profiles.flops_torch    count_torch(model) -> FlopCount          (imports torch)
    e3dpsm.profiles.flops_onnx     count_onnx(graph or path) -> FlopCount   (torch-free)
    e3dpsm.profiles.graph_groups   ONNX node -> module group
    e3dpsm.profiles.targets        targets.toml: load_targets, select_targets, availability
    e3dpsm.profiles.devices        devices.toml: load_devices, roofline
    e3dpsm.profiles.latency        runners per runtime, measure_side_by_side, matmul peak
    e3dpsm.profiles.memory         RssSampler
    e3dpsm.profiles.inputs         synthetic or prepared LNES frames
    e3dpsm.profiles.ort_profile    onnxruntime profiling trace -> ms per op type / module
    e3dpsm.profiles.profiler       profile_targets: the body of `e3dpsm profile`
    e3dpsm.profiles.report         report.md and plots
"""
from e3dpsm.profiles.devices import Device, load_devices, roofline
from e3dpsm.profiles.flops import MODULE_GROUPS, PAPER_EFFICIENCY, FlopCount, ModuleCount
from e3dpsm.profiles.targets import Availability, Target, availability, load_targets, select_targets

__all__ = [
    "Availability", "Device", "FlopCount", "MODULE_GROUPS", "ModuleCount", "PAPER_EFFICIENCY", "Target",
    "availability", "load_devices", "load_targets", "roofline", "select_targets",
]
