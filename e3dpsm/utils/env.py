"""What every report records about where it was produced: versions, machine, threads."""
from __future__ import annotations

import datetime as _dt
import importlib.metadata
import os
import platform
import sys
from typing import Any

_PACKAGES = ("e3dpsm", "torch", "numpy", "onnx", "onnxruntime", "onnxsim", "openvino", "pandas",
             "executorch", "litert-torch", "ai-edge-litert", "coremltools", "tensorrt")

# `--device` of the commands that train (train, distill): auto is CUDA where torch sees a GPU.
DEVICE_CHOICES: tuple[str, ...] = ("auto", "cpu", "cuda")


def package_versions() -> dict[str, str | None]:
    versions: dict[str, str | None] = {}
    for name in _PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def machine_info() -> dict[str, Any]:
    info: dict[str, Any] = {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or None,
        "python": sys.version.split()[0],
        "cpu_count": os.cpu_count(),
    }
    try:
        import psutil

        info["memory_gb"] = round(psutil.virtual_memory().total / 2**30, 1)
    except ImportError:  # psutil is a dependency; keep reports working without it anyway
        pass
    from e3dpsm.utils.isa import detect_isa

    info["isa"] = detect_isa().to_dict()  # INT8 / bf16 speed and error depend on it (utils/isa.py)
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return info


def report_header(command: str, config: dict[str, Any] | None = None) -> dict[str, Any]:
    """The common head of every JSON report: what ran, with which config, where, when."""
    return {
        "command": command,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "config": config or {},
        "versions": package_versions(),
        "machine": machine_info(),
    }
