"""Tolerance profiles of `golden check`: what "matches the golden rollout" means for a graph.

- fp32: the parity tolerances (`e3dpsm parity`): every pose output within 0.01 mm of the
  golden one at every step, every state within 1e-4 of its magnitude (max |diff| over the
  tensor / max |golden| over the tensor) at every step.
- fp16, int8, bf16 (compressed graphs): the accuracy budget (task metrics against the golden's
  fp32 poses, e3dpsm/budget.py) and the host's rollout of the same graph (host.py) decide;
  the profile bounds the states: every state's relative RMS error (||diff|| / ||golden|| over
  the recorded elements) stays below `state_rtol` at every step, and does not grow: over the
  last quarter of the rollout its median is at most `max_growth` times its median over the
  first quarter. A compressed recurrent state that wanders off fails even while the poses
  still look good. Both medians are first raised to `growth_floor` (a tenth of
  `state_rtol`): a state well under a per cent from fp32 throughout has not wandered off,
  whatever the ratio of two such small numbers (a weight-only INT8 `.tflite` of `small`: x5.85
  on an S5 state whose distance stayed under 1.4%, while its poses matched the host's
  to 7e-5 mm on emulated ARM); INT8 states sit 0.1-0.5 away from the first step.

Why these numbers: the max-abs measure of fp32 parity does not suit a quantised state (the
trained tiny's INT8 graph misses the largest element of an S5 state by 0.3-1.2 of its
magnitude from the first step, while its RMS error stays near 0.1: measured with `golden
check` and `e3dpsm diagnose`). An RMS error of half the state's own size means the state
carries little of the reference; fp16 keeps the recurrence in float32, so its states stay
within a few per cent. What separates a healthy quantised recurrence from an unstable one
is growth, hence the growth bound on both.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any, Mapping

from e3dpsm.errors import InputError


@dataclass(frozen=True)
class ToleranceProfile:
    name: str
    kind: str  # "exact": per-step absolute limits | "budget": the accuracy budget decides
    pose_atol_mm: float | None = None  # exact
    state_rtol: float = 1e-4  # per step; exact: max |diff| / max |golden|, budget: relative RMS
    max_growth: float | None = None  # budget: late / early median state error
    growth_floor: float | None = None  # budget: state errors below it are noise to the growth bound

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if v is not None}

    @classmethod
    def from_dict(cls, entry: Mapping[str, Any]) -> "ToleranceProfile":
        try:
            return cls(**{k: entry[k] for k in entry if k in cls.__dataclass_fields__})
        except TypeError as exc:
            raise InputError(f"broken tolerance profile {dict(entry)}: {exc}") from exc


PROFILES: dict[str, ToleranceProfile] = {
    "fp32": ToleranceProfile("fp32", "exact", pose_atol_mm=0.01, state_rtol=1e-4),
    "fp16": ToleranceProfile("fp16", "budget", state_rtol=0.05, max_growth=4.0, growth_floor=0.005),
    "int8": ToleranceProfile("int8", "budget", state_rtol=0.5, max_growth=4.0, growth_floor=0.05),
}
# An fp32 graph run in bf16 (8-bit mantissa, OpenVINO's INFERENCE_PRECISION_HINT=bf16 on a
# CPU with bf16 units): the int8 budget, since both keep about 8 bits per value; its
# recurrent states are rounded too, hence the int8 state bound.
PROFILES["bf16"] = replace(PROFILES["int8"], name="bf16")

# A quantised graph names its mode in its metadata; the mode decides its profile. Weight-only
# INT8 (float arithmetic) is held to the INT8 budget; its tolerance to the host's rollout
# across ISAs is fp32's (golden/host.kernel_parity_for).
MODE_PROFILES = {"int8": "int8", "int8-dynamic": "int8", "int8-weights": "int8", "fp16": "fp16"}


def profile_for_quantization(quantization: Mapping[str, Any] | None) -> str:
    """The profile name a graph gets by default: fp32 unless its metadata says otherwise."""
    if not quantization:
        return "fp32"
    mode = str(quantization.get("mode", ""))
    if mode not in MODE_PROFILES:
        raise InputError(f"the graph's quantisation mode {mode!r} has no golden profile; pass --profile")
    return MODE_PROFILES[mode]
