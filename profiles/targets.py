"""Deployment targets (profiles/targets.toml) and whether each can run on this machine."""
from __future__ import annotations

import importlib.util
import sys
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

from e3dpsm.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

# openvino-stateful: the graph converted to a stateful IR (states as OpenVINO variables);
# executorch / litert: a converted edge artifact (.pte / .tflite, `e3dpsm convert`), given
# to `profile --edge-models`, on the XNNPACK CPU backend.
RUNTIMES = ("torch", "onnxruntime", "openvino", "openvino-stateful", "executorch", "litert")
EDGE_RUNTIMES = {"executorch": ("executorch", ".pte"), "litert": ("ai_edge_litert", ".tflite")}
# bf16: the fp32 graph with its float parts in bf16 (OpenVINO on CPUs with bf16 units).
PRECISIONS = ("fp32", "fp16", "int8", "bf16")
GRAPHS = ("none", "fp32", "fp16", "int8")
# The fp32 graph exported with `e3dpsm export --static-batch` (batch fixed to 1): the key
# static targets look their graph up by (Target.graph_key).
STATIC_FP32 = "fp32-static"
GRAPH_HINTS = {
    "int8": "no int8 graph: run e3dpsm quantize first or pass --int8-model",
    "fp16": "no fp16 graph: run e3dpsm quantize first or pass --fp16-model",
    "fp32": "no fp32 graph: pass --model or --variant/--checkpoint",
    STATIC_FP32: "no static-batch graph: pass --static-model (e3dpsm export --static-batch) with --model, "
                 "or --variant/--checkpoint to export it here",
    "none": "no PyTorch model: --model gives a graph only; use --variant or --checkpoint",
}


@dataclass(frozen=True)
class Target:
    name: str
    runtime: str
    provider: str
    precision: str
    graph: str
    threads: int
    options: Mapping[str, str] = field(default_factory=dict)
    static_batch: bool = False  # the --static-batch export of the graph (batch 1, fewer shape ops)

    @property
    def graph_key(self) -> str:
        """Which file of the profile's `graphs` mapping the target loads: "<runtime>/<precision>"
        for an edge artifact, the static-batch graph for static targets, else the graph kind."""
        if self.runtime in EDGE_RUNTIMES:
            return f"{self.runtime}/{self.graph}"
        return STATIC_FP32 if self.static_batch else self.graph

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "runtime": self.runtime, "provider": self.provider,
                "precision": self.precision, "graph": self.graph, "static_batch": self.static_batch,
                "threads": self.threads, "options": dict(self.options)}


@dataclass(frozen=True)
class Availability:
    available: bool
    reason: str | None = None


def _target_from_entry(entry: Mapping[str, Any], source: str) -> Target:
    try:
        target = Target(
            name=str(entry["name"]), runtime=str(entry["runtime"]), provider=str(entry["provider"]),
            precision=str(entry["precision"]), graph=str(entry.get("graph", "fp32")),
            threads=int(entry.get("threads", 2)),
            options={str(k): str(v) for k, v in dict(entry.get("options", {})).items()},
            static_batch=_boolean(entry.get("static_batch", False), f"{source}: target {entry.get('name')!r}"),
        )
    except KeyError as exc:
        raise ConfigError(f"{source}: target {dict(entry).get('name', '?')!r} lacks field {exc.args[0]!r}") from None
    for value, allowed, what in ((target.runtime, RUNTIMES, "runtime"), (target.precision, PRECISIONS, "precision"),
                                 (target.graph, GRAPHS, "graph")):
        if value not in allowed:
            raise ConfigError(f"{source}: target {target.name!r} has {what} {value!r}; expected one of {list(allowed)}")
    if target.threads <= 0:
        raise ConfigError(f"{source}: target {target.name!r} needs threads >= 1")
    if target.static_batch and target.graph != "fp32":
        # The profile exports the static graph itself from the PyTorch model; a static int8 /
        # fp16 graph would need its own quantisation run and flag.
        raise ConfigError(f"{source}: target {target.name!r}: static_batch applies to the fp32 graph only, "
                          f"not {target.graph!r}")
    return target


def _boolean(value: Any, where: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{where}: static_batch must be true or false, got {value!r}")
    return value


def load_targets(path: str | Path | None = None) -> dict[str, Target]:
    """Targets by name from a TOML file (default: the packaged profiles/targets.toml)."""
    if path is None:
        text = resources.files("e3dpsm.profiles").joinpath("targets.toml").read_text(encoding="utf-8")
        source = "targets.toml"
    else:
        try:
            text, source = Path(path).read_text(encoding="utf-8"), str(path)
        except OSError as exc:
            raise ConfigError(f"cannot read targets file {path}: {exc.strerror}") from None
    try:
        entries = tomllib.loads(text).get("target", [])
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source} is not valid TOML: {exc}") from None
    targets = [_target_from_entry(entry, source) for entry in entries]
    names = [t.name for t in targets]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ConfigError(f"{source}: duplicate target names {duplicates}")
    return {t.name: t for t in targets}


def select_targets(known: Mapping[str, Target], spec: str, threads: int | None = None) -> list[Target]:
    """`a,b,c` or `all` -> targets in that order; `threads` overrides every target's count."""
    names = list(known) if spec.strip() == "all" else [n.strip() for n in spec.split(",") if n.strip()]
    if not names:
        raise ConfigError(f"--targets is empty; known targets: {', '.join(known)} (or 'all')")
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ConfigError(f"unknown target(s) {', '.join(unknown)}; known targets: {', '.join(known)} (or 'all')")
    chosen = [known[n] for n in dict.fromkeys(names)]
    return [replace(t, threads=threads) for t in chosen] if threads else chosen


def runtime_availability(target: Target) -> Availability:
    """Can this machine run the target's runtime and provider (independent of any graph)?"""
    if target.runtime in EDGE_RUNTIMES:
        from e3dpsm.utils.extras import missing_reason

        reason = missing_reason(EDGE_RUNTIMES[target.runtime][0], f"for target {target.name}")
        return Availability(reason is None, reason)
    module = {"torch": "torch", "onnxruntime": "onnxruntime", "openvino": "openvino",
              "openvino-stateful": "openvino"}[target.runtime]
    if importlib.util.find_spec(module) is None:
        return Availability(False, f"{module} is not installed")
    if target.runtime == "onnxruntime":
        import onnxruntime as ort

        providers = ort.get_available_providers()
        if target.provider not in providers:
            return Availability(False, f"{target.provider} not in onnxruntime.get_available_providers() {providers}")
    elif target.runtime in ("openvino", "openvino-stateful"):
        import openvino as ov

        devices = ov.Core().available_devices
        if target.provider not in devices:
            return Availability(False, f"OpenVINO device {target.provider} not in Core().available_devices {devices}")
        if target.precision == "bf16" and target.provider == "CPU":
            from e3dpsm.utils.isa import bf16_unavailable_reason

            reason = bf16_unavailable_reason()
            if reason:
                return Availability(False, reason)
    elif target.provider != "cpu":
        return Availability(False, f"torch target provider {target.provider!r} is not supported (only 'cpu')")
    return Availability(True)


def availability(target: Target, graphs: Mapping[str, Path | None], has_torch_model: bool) -> Availability:
    """Runtime first (the more fundamental reason), then the graph the target loads."""
    runtime = runtime_availability(target)
    if not runtime.available:
        return runtime
    if target.graph == "none":
        return Availability(True) if has_torch_model else Availability(False, GRAPH_HINTS["none"])
    if target.runtime in EDGE_RUNTIMES and graphs.get(target.graph_key) is None:
        suffix = EDGE_RUNTIMES[target.runtime][1]
        return Availability(False, f"no {target.graph} {suffix}: pass --edge-models STEP{suffix} "
                                   f"(e3dpsm convert {target.runtime})")
    if graphs.get(target.graph_key) is None:
        return Availability(False, GRAPH_HINTS[target.graph_key])
    return Availability(True)
