"""One pruning round's plan: which units to cut, and how far, to reach the round's target.

Candidates: every unit narrowed by the round's shrink factor (widths kept at multiples of
`align` channels, which vector kernels like), and every removable unit removed. Each
candidate is applied alone (surgery, compress/surgery.py) and its damage measured: the mean
joint distance (mm) between its fused poses and the current model's on calibration frames,
streamed causally as deployed. Its gain is what it saves: step milliseconds by the latency
model (compress/latency.py) for a latency target, MACs for a MACs target.

Greedy: candidates by damage per unit of gain, at most one per unit (none inside a removed
block), until the predicted step or the counted MACs reach the round's target. The gain is
the step time the latency model says a cut saves, whatever the target: the latency model
decides where to cut, the target how far. (MACs only break ties, ranking the cuts that save
no measured time last: on the trained `small` at 2 threads, half the MACs narrowed away
saves under a tenth of the step, docs/compress.md.)
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping, Sequence

import torch

from e3dpsm.compress.importance import keep_lists
from e3dpsm.compress.latency import LatencyProfile, predict_ms
from e3dpsm.compress.surgery import prune_model
from e3dpsm.compress.units import ATTN_BLOCK, Unit, prunable_units
from e3dpsm.models import E3DPSM


@dataclass(frozen=True)
class Candidate:
    unit: str
    width: int  # new width (0: removed)
    old_width: int
    damage_mm: float
    saved_macs: int
    saved_ms: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@torch.no_grad()
def count_macs(model: E3DPSM) -> dict[str, int]:
    """Multiply-accumulates of one batch-1 step per Conv2d / Linear module path (the layers
    pruning changes; the sampling, S5 recurrence and elementwise work are not counted)."""
    macs: dict[str, int] = {}
    hooks = []
    for name, module in model.named_modules():
        if isinstance(module, torch.nn.Conv2d):
            def conv_hook(mod, _inp, out, name=name):
                k = mod.kernel_size[0] * mod.kernel_size[1] * mod.in_channels // mod.groups
                macs[name] = macs.get(name, 0) + out.numel() * k
            hooks.append(module.register_forward_hook(conv_hook))
        elif isinstance(module, torch.nn.Linear):
            def linear_hook(mod, _inp, out, name=name):
                macs[name] = macs.get(name, 0) + out.numel() * mod.in_features
            hooks.append(module.register_forward_hook(linear_hook))
    cfg = model.config
    try:
        was_training = model.training
        model.eval()
        model.step(torch.zeros(1, cfg.in_channels, cfg.height, cfg.width), model.init_state(1))
        model.train(was_training)
    finally:
        for hook in hooks:
            hook.remove()
    return macs


def total_macs(model: E3DPSM) -> int:
    return sum(count_macs(model).values())


def macs_per_stage(model: E3DPSM) -> dict[str, int]:
    """MACs by top-level group: stem, stage i (its convs, deformable block, S5), decoder, heads."""
    out: dict[str, int] = {}
    for name, value in count_macs(model).items():
        parts = name.split(".")
        if parts[0] in ("stages", "attention", "ssm"):
            key = f"stage{int(parts[1]) + 1}"
        else:
            key = "decoder+heads" if parts[0] != "stem" else "stem"
        out[key] = out.get(key, 0) + value
    return out


def _aligned(width: int, shrink: float, align: int) -> int:
    target = width * shrink
    if width <= align:
        return max(1, int(math.floor(target)))
    return max(align, int(math.floor(target / align)) * align)


def candidate_widths(unit: Unit, shrink: float, align: int) -> list[int]:
    """The widths a round tries for `unit`: an attention block removed; any other unit narrowed
    by `shrink` (aligned) where that narrows it, and removed where it may be."""
    if unit.kind == ATTN_BLOCK:
        return [0]
    widths = []
    narrowed = _aligned(unit.width, shrink, align)
    if narrowed < unit.width:
        widths.append(narrowed)
    if unit.removable:
        widths.append(0)
    return widths


@torch.no_grad()
def pose_distance_mm(a: Mapping[str, torch.Tensor], b: Mapping[str, torch.Tensor]) -> float:
    return float((a["pose"] - b["pose"]).norm(dim=-1).mean())


@torch.no_grad()
def measure_candidates(model: E3DPSM, frames: torch.Tensor, window_ms: float, shrink: float, align: int,
                       profile: LatencyProfile | None) -> list[Candidate]:
    """Every candidate cut of `model`, applied alone, with its damage and gains.
    frames: [B, T, 2, H, W] calibration windows, streamed causally."""
    model.eval()
    units = prunable_units(model.config)
    reference = model.forward_sequence(frames, causal=True, window_ms=window_ms)
    base_macs = total_macs(model)
    out: list[Candidate] = []
    for unit in units:
        for width in candidate_widths(unit, shrink, align):
            pruned = prune_model(model, keep_lists(model, units, {unit.name: width})).eval()
            damage = pose_distance_mm(pruned.forward_sequence(frames, causal=True, window_ms=window_ms), reference)
            saved = profile.run_ms - predict_ms(profile, units, {unit.name: width}) if profile else 0.0
            out.append(Candidate(unit.name, width, unit.width, damage, base_macs - total_macs(pruned), saved))
    return out


def choose(candidates: Sequence[Candidate], units: Sequence[Unit], objective: str, current: float, target: float,
           profile: LatencyProfile | None = None) -> tuple[dict[str, int], float]:
    """Greedy choice (module docstring): new widths and the predicted objective after them.
    objective "macs": `current`/`target` in MACs; "latency": in ms (needs `profile`)."""
    if objective not in ("macs", "latency"):
        raise ValueError(f"unknown objective {objective!r}")
    scopes = {u.name: u.scope for u in units}

    base_ms = profile.run_ms if profile is not None and profile.run_ms > 0 else 1.0
    base_macs = max(max((c.saved_macs for c in candidates), default=1), 1)

    def gain(c: Candidate) -> float:
        return c.saved_ms / base_ms + 1e-3 * c.saved_macs / base_macs

    useful = [c for c in candidates if (c.saved_macs if objective == "macs" else c.saved_ms) > 0]
    ranked = sorted(useful, key=lambda c: (c.damage_mm / gain(c), c.unit, c.width))
    chosen: dict[str, int] = {}
    value = current
    for cand in ranked:
        if value <= target:
            break
        if cand.unit in chosen:
            continue
        # Nothing inside a removed block, and no block removed around a chosen unit.
        inside = [n for n, w in chosen.items() if w == 0 and scopes[cand.unit].startswith(scopes[n])]
        around = [n for n in chosen if cand.width == 0 and scopes[n].startswith(scopes[cand.unit])]
        if inside or around:
            continue
        chosen[cand.unit] = cand.width
        if objective == "latency":
            value = predict_ms(profile, units, chosen)
        else:
            value -= cand.saved_macs
    return chosen, value
