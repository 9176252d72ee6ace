"""Reference devices (profiles/devices.toml) and a roofline estimate of their pose rate.

Roofline: time per step >= max(FLOPs / peak compute, bytes moved / bandwidth), so
Hz <= min(peak / FLOPs, bandwidth / bytes). An upper bound that ignores kernel-launch and
framework overhead, which dominate a small batch-1 model on a large GPU: it is labelled as
an estimate everywhere and shown next to the paper's measured rates.
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from typing import Any

from e3dpsm.errors import ConfigError
from e3dpsm.profiles.targets import tomllib

BYTES_PER_VALUE = {"fp32": 4, "fp16": 2, "int8": 1}


@dataclass(frozen=True)
class Device:
    name: str
    fp32_tflops: float
    bandwidth_gbs: float
    fp16_tflops: float | None = None
    int8_tops: float | None = None
    measured_hz: float | None = None

    def peak_ops(self, precision: str) -> float:
        """Peak operations per second at `precision`, falling back to FP32 if none is listed."""
        tera = {"fp32": self.fp32_tflops, "fp16": self.fp16_tflops, "int8": self.int8_tops}.get(precision)
        return (tera or self.fp32_tflops) * 1e12


def load_devices() -> list[Device]:
    text = resources.files("e3dpsm.profiles").joinpath("devices.toml").read_text(encoding="utf-8")
    try:
        return [Device(**entry) for entry in tomllib.loads(text).get("device", [])]
    except TypeError as exc:
        raise ConfigError(f"devices.toml: bad device entry ({exc})") from None


def bytes_per_step(weight_values: int, activation_values: int, state_values: int, precision: str = "fp32") -> int:
    """Weights read once, every activation written and read once, states read and written
    (states stay float32 in every graph)."""
    size = BYTES_PER_VALUE[precision]
    return weight_values * size + 2 * activation_values * size + 2 * state_values * 4


def roofline(device: Device, flops: float, bytes_moved: float, precision: str = "fp32") -> dict[str, Any]:
    compute_hz = device.peak_ops(precision) / flops
    memory_hz = device.bandwidth_gbs * 1e9 / bytes_moved
    return {
        "device": device.name, "precision": precision, "estimate": True,
        "compute_bound_hz": compute_hz, "bandwidth_bound_hz": memory_hz,
        "hz_estimate": min(compute_hz, memory_hz),
        "bound": "compute" if compute_hz < memory_hz else "bandwidth",
        "paper_measured_hz": device.measured_hz,
    }
