"""`e3dpsm convert coreml`: the step graph as a Core ML ML program (`step.mlpackage`),
states as explicit inputs and outputs under the ONNX graph's names, fp16 or fp32 compute,
the state layout in the package's user-defined metadata (`e3dpsm`).

Core ML predicts only on macOS; on Linux `check_package` checks what can be checked without
predicting: input / output names, shapes and types against the I/O spec, the operators of
the ML program, and how many of the checkpoint's convolution and linear weights it stores
as they are.

The literal GridSample form converts (to Core ML's `resample`); the gather form's folded
projections multiply parameters by parameters, a matrix-vector matmul coremltools 9 does not
convert, so grid_sample is the form here. An output that is the same tensor as another (the
fused pose is also the fusion state) is one Core ML output: the package keeps the first name
and the metadata records the alias, which the runner copies."""
from __future__ import annotations

import os
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from e3dpsm.errors import ConfigError
from e3dpsm.export.edge_export import NamedStepGraph, artifact_contract, export_ready
from e3dpsm.models import E3DPSM
from e3dpsm.runtime.artifact_metadata import EMBEDDED_NAME, encode
from e3dpsm.utils.extras import require

FORMAT = "coreml"
PRECISIONS = ("fp16", "fp32")
WEIGHT_RTOL = {"fp16": 1e-3, "fp32": 1e-6}  # fp16 keeps 11 significant bits


@dataclass(frozen=True)
class CoreMLOptions:
    attention_form: str = "grid_sample"
    precision: str = "fp16"


@dataclass
class CoreMLResult:
    path: str
    bytes: int
    seconds: dict[str, float]
    checks: dict[str, Any]
    options: dict[str, Any]
    artifact: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dict(vars(self))


class _DistinctOutputs(torch.nn.Module):
    """The named step without the outputs that alias an earlier one."""

    def __init__(self, named: NamedStepGraph, dropped: set[str]) -> None:
        super().__init__()
        self.named, self.dropped = named, dropped

    def forward(self, **inputs: torch.Tensor) -> dict[str, torch.Tensor]:
        return {k: v for k, v in self.named(**inputs).items() if k not in self.dropped}


def output_aliases(named: NamedStepGraph) -> dict[str, str]:
    """{output: the earlier output it is the same tensor as}, from one eager step."""
    with torch.no_grad():
        outputs = named(**named.example_kwargs())
    first: dict[int, str] = {}
    aliases = {}
    for name, value in outputs.items():
        if id(value) in first:
            aliases[name] = first[id(value)]
        else:
            first[id(value)] = name
    return aliases


def _package_bytes(path: str | os.PathLike) -> int:
    return sum(f.stat().st_size for f in os.scandir(path) for f in _walk(f))


def _walk(entry: os.DirEntry) -> list[os.DirEntry]:
    if entry.is_dir():
        return [g for f in os.scandir(entry.path) for g in _walk(f)]
    return [entry]


def convert_coreml(model: E3DPSM, path: str | os.PathLike, options: CoreMLOptions = CoreMLOptions()) -> CoreMLResult:
    ct = require("coremltools", "to write .mlpackage programs")
    if options.precision not in PRECISIONS:
        raise ConfigError(f"unknown Core ML precision {options.precision!r}; choose one of {', '.join(PRECISIONS)}")
    if options.attention_form != "grid_sample":
        raise ConfigError("Core ML takes the grid_sample attention form (the gather form's folded projections do "
                          "not convert with coremltools 9); pass --attention-form grid_sample")
    named = NamedStepGraph(model).eval()
    started = time.perf_counter()
    with export_ready(model, options.attention_form):
        aliases = output_aliases(named)
        module = _DistinctOutputs(named, set(aliases))
        program = torch.export.export(module, (), named.example_kwargs(), strict=False).run_decompositions({})
        names = [n for n in named.spec.output_names if n not in aliases]
        package = ct.convert(
            program, outputs=[ct.TensorType(name=n, dtype=np.float32) for n in names], convert_to="mlprogram",
            compute_precision=ct.precision.FLOAT16 if options.precision == "fp16" else ct.precision.FLOAT32,
            minimum_deployment_target=ct.target.iOS17)
    converted = time.perf_counter()
    meta, record = artifact_contract(model, FORMAT, options.precision, options.attention_form,
                                     ("coremltools",), {"output_aliases": aliases})
    package.user_defined_metadata[EMBEDDED_NAME] = encode(meta, record)
    checks = check_package(package, model, named.spec, aliases, options.precision)
    package.save(str(path))  # the CLI writes into a folder renamed into place when complete
    done = time.perf_counter()
    return CoreMLResult(
        path=str(path), bytes=_package_bytes(path), checks=checks, options=vars(options).copy(), artifact=record,
        seconds={"convert": round(converted - started, 2), "save": round(done - converted, 2),
                 "total": round(done - started, 2)},
    )


def check_package(package: Any, model: E3DPSM, spec: Any, aliases: dict[str, str], precision: str) -> dict[str, Any]:
    """The Linux-side checks (module doc); raises nothing, returns {check: result, passed}."""
    description = package.get_spec().description
    got_inputs = {i.name: list(i.type.multiArrayType.shape) for i in description.input}
    got_outputs = {o.name: list(o.type.multiArrayType.shape) for o in description.output}
    want_inputs = {t.name: list(t.shape) for t in spec.inputs}
    want_outputs = {t.name: list(t.shape) for t in spec.outputs if t.name not in aliases}
    float32 = 65568  # ArrayFeatureType.FLOAT32
    types_ok = all(i.type.multiArrayType.dataType == float32 for i in (*description.input, *description.output))
    operations = package._mil_program.functions["main"].operations
    weights = weights_in_package(operations, model, WEIGHT_RTOL[precision])
    io_ok = got_inputs == want_inputs and got_outputs == want_outputs
    return {
        "inputs": {"expected": want_inputs, "found": got_inputs},
        "outputs": {"expected": want_outputs, "found": got_outputs, "aliases": aliases},
        "io_matches_spec": io_ok, "float32_io": types_ok,
        "operators": dict(Counter(op.op_type for op in operations).most_common()),
        "weights": weights,
        "passed": io_ok and types_ok,
    }


def weights_in_package(operations: Any, model: E3DPSM, rtol: float) -> dict[str, Any]:
    """Every convolution and linear weight of the model against the program's constants of
    the same shape: found when one equals it within `rtol` of its largest value. Not all are
    stored as they are: coremltools folds some into their neighbours (a convolution with the
    BatchNorm after it, the offsets' in-graph rescaling, the decoder's scaled queries), and
    those are listed as `missing`, so the figure is a check that the weights are the
    checkpoint's (a wrong checkpoint finds almost none), not a pass/fail of its own."""
    consts: dict[tuple[int, ...], list[np.ndarray]] = {}
    for op in operations:
        if op.op_type == "const" and op.outputs[0].val is not None and np.ndim(op.outputs[0].val) >= 2:
            value = np.asarray(op.outputs[0].val, dtype=np.float32)
            consts.setdefault(value.shape, []).append(value)
    modules = [(n, m.weight) for n, m in model.named_modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]
    missing = []
    for name, weight in modules:
        want = weight.detach().float().numpy()
        scale = max(float(np.abs(want).max()), 1e-12)
        if not any(np.max(np.abs(c - want)) <= rtol * scale for c in consts.get(want.shape, [])):
            missing.append(name)
    return {"checked": len(modules), "found": len(modules) - len(missing), "missing": missing}
