"""Counting convention, module groups and the formulas shared by the PyTorch and ONNX counters.

Convention (one place; both counters and every report use it):
- MACs per pose update (one `step`, batch 1). FLOPs = 2 x MACs, as ptflops / fvcore report
  MACs and `torch.utils.flop_counter.FlopCounterMode` reports 2 x MACs.
- "dense": Conv, Gemm / Linear and MatMul multiply-accumulates, exact (bias adds excluded).
- "sampling": GridSample bilinear interpolation, BILINEAR_TAPS MACs per sampled value per
  channel (four weighted taps); counters miss it, so it is counted by formula.
- "recurrence": the S5 state update and the Kalman fusion, element-wise work that counters
  miss, counted by formula from the state layout (below).
- MACs = dense + sampling + recurrence. Other element-wise work (normalisations,
  activations, residual adds, softmax, the attention weighting) is not in MACs; the ONNX
  counter reports it separately as "elementwise" (one op per output value of such nodes).

The paper's 8.16 GFLOPs (Table 5, App. C) are FLOPs = 2 x MACs over the 2-frame input that the
released `compute_performance_metrics.py` counts (docs/model.md#citations, Efficiency):
comparable with it is 2 x MACs x PAPER_FRAMES of ours.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from e3dpsm.state import StateSpec

# Module groups of the paper's efficiency table -> top-level attributes of the E3DPSM model,
# which are also the first component of the ONNX node names' module scope (`/stages.0/...`).
MODULE_GROUPS: dict[str, tuple[str, ...]] = {
    "cnn": ("stem", "stages"),
    "deformable_attention": ("attention",),
    "ssm": ("ssm",),
    "query_decoder": ("decoder",),
    "heads": ("direct_head", "pose_embed", "delta_head"),
    "fusion": ("fusion",),
}
OTHER = "other"
GROUP_NAMES: tuple[str, ...] = (*MODULE_GROUPS, OTHER)
CATEGORIES: tuple[str, ...] = ("dense", "sampling", "recurrence")

BILINEAR_TAPS = 4
# S5, per spatial location and state mode: gamma * (B u) and Lambda_bar * x + v are complex
# products, 4 real MACs each.
S5_MACS_PER_MODE = 8
# Element-wise Kalman filter per pose coordinate, multiplies and divides (adds folded in):
# gain P/(P+R) 1, update K*(z-x) 1, Joseph form (1-K)^2 P + K^2 R 4, first-step selection of
# pose and covariance 2 x 2.
KALMAN_MACS_PER_COORD = {"learned": 10, "static": 10, "naive": 2, "direct": 0}

PAPER_FRAMES = 2
PAPER_EFFICIENCY: dict[str, Any] = {
    "source": "E-3DPSM paper, efficiency table (one A6000); FLOPs = 2 x MACs over a 2-frame input",
    "params_m": 6.64,
    "gflops": 8.16,
    "gflops_per_module": {
        "cnn": 7.05, "deformable_attention": 0.89, "ssm": 0.06, "query_decoder": 0.15,
        "heads": 1e-3, "fusion": 1e-4,
    },
    "gpu_memory_mb": 74,
    "hz_measured": {"A6000": 80, "RTX 3050 Ti": 51, "Jetson Orin Nano": 30},
}

_S5_STATE = re.compile(r"^s5_stage(\d+)_re$")


def group_of(attribute: str) -> str:
    """Module group of a top-level model attribute (`stages`, `ssm`, ...); OTHER if none."""
    for group, attributes in MODULE_GROUPS.items():
        if attribute in attributes:
            return group
    return OTHER


def grid_sample_macs(batch: int, channels: int, out_h: int, out_w: int) -> int:
    """Bilinear GridSample producing [batch, channels, out_h, out_w]."""
    return BILINEAR_TAPS * batch * channels * out_h * out_w


def recurrence_macs(states: Sequence[StateSpec], model_config: Mapping[str, Any]) -> dict[str, int]:
    """Formula MACs of the S5 recurrences and the fusion, from the state layout (batch 1).

    `states` comes from `model.state_spec()` or the graph metadata, `model_config` from
    `config.to_dict()` or the metadata's `model_config`, so both counters share this code.
    """
    widths = list(model_config["widths"])
    counts = {"ssm": 0, "fusion": 0}
    for spec in states:
        match = _S5_STATE.match(spec.name)
        if match:
            *spatial, modes = spec.shape
            channels = widths[int(match.group(1)) - 1]
            # + D u, one MAC per location and channel
            counts["ssm"] += math.prod(spatial) * (S5_MACS_PER_MODE * modes + channels)
        elif spec.name == "fusion_pose":
            mode = str(model_config.get("fusion", "learned"))
            counts["fusion"] += math.prod(spec.shape) * KALMAN_MACS_PER_COORD.get(mode, 0)
    return counts


@dataclass
class ModuleCount:
    """Counts of one module group, per category of the convention (MACs), plus parameters."""

    dense: int = 0
    sampling: int = 0
    recurrence: int = 0
    elementwise: int | None = None  # ONNX counter only; not part of MACs
    params: int | None = None

    @property
    def macs(self) -> int:
        return self.dense + self.sampling + self.recurrence

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"macs": self.macs, "flops": 2 * self.macs, "dense": self.dense,
                               "sampling": self.sampling, "recurrence": self.recurrence}
        if self.elementwise is not None:
            out["elementwise"] = self.elementwise
        if self.params is not None:
            out["params"] = self.params
        return out


@dataclass
class FlopCount:
    """Per-module counts of one pose update, from one counter ("pytorch" or "onnx")."""

    source: str
    modules: dict[str, ModuleCount] = field(default_factory=lambda: {g: ModuleCount() for g in GROUP_NAMES})
    notes: list[str] = field(default_factory=list)

    @property
    def macs(self) -> int:
        return sum(m.macs for m in self.modules.values())

    @property
    def flops(self) -> int:
        return 2 * self.macs

    @property
    def params(self) -> int | None:
        values = [m.params for m in self.modules.values() if m.params is not None]
        return sum(values) if values else None

    def add(self, group: str, category: str, value: int) -> None:
        module = self.modules[group]
        setattr(module, category, (getattr(module, category) or 0) + int(value))

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source, "macs": self.macs, "flops": self.flops, "params": self.params,
            "paper_convention_gflops": paper_convention_gflops(self.macs),
            "modules": {g: m.to_dict() for g, m in self.modules.items()}, "notes": list(self.notes),
        }


def paper_convention_gflops(macs: int) -> float:
    """Our per-update MACs in the paper's unit: 2 x MACs over a 2-frame input, in G."""
    return 2 * macs * PAPER_FRAMES / 1e9


def relative_difference(a: float, b: float) -> float:
    return abs(a - b) / max(abs(a), abs(b), 1e-30)
