"""One call that checks a graph file against a golden folder and writes the verdict: what
`e3dpsm golden check`, `e3dpsm.testing.assert_golden` and the pipeline share."""
from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from typing import Any, Sequence

from e3dpsm.errors import InputError
from e3dpsm.golden.artifact_trace import trace_module
from e3dpsm.golden.check import GoldenCheck, check_golden, plot_check
from e3dpsm.golden.store import GoldenRecord, load_golden
from e3dpsm.golden.tolerances import PROFILES, ToleranceProfile, profile_for_quantization
from e3dpsm.runtime.stepping import GraphStepper

# "openvino-bf16": the graph's float parts in bf16 on a CPU with bf16 units (held to the bf16
# profile by default, since the graph itself says fp32).
RUNTIMES = ("onnxruntime", "openvino", "openvino-bf16")
CHECK_FILE = "check.json"
PLOT_FILE = "check.png"


def artifact_check_runtime(model: str | os.PathLike, runtime: str) -> str:
    """The runtime a check of `model` runs on: an ONNX graph's is `runtime`; any other
    artifact has its own, by extension (.pte: executorch, .tflite: litert, ...)."""
    from e3dpsm.runtime.stepping import artifact_runtime

    own = artifact_runtime(model)
    if own == "onnxruntime":
        if runtime not in RUNTIMES:
            raise InputError(f"unknown runtime {runtime!r}; choose one of {', '.join(RUNTIMES)}")
        return runtime
    if runtime not in ("onnxruntime", own):
        raise InputError(f"{model} runs on {own}, not {runtime}; leave --runtime out for it")
    return own


def open_runner(model: str | os.PathLike, runtime: str = "onnxruntime", *, threads: int | None = None,
                providers: Sequence[str] | None = None) -> GraphStepper:
    """`runtime` for an ONNX graph; any other artifact on its own runtime (open_stepper)."""
    runtime = artifact_check_runtime(model, runtime)
    if runtime not in RUNTIMES or runtime == "onnxruntime":
        from e3dpsm.runtime.stepping import open_stepper

        if providers and runtime != "onnxruntime":
            raise InputError(f"--providers applies to onnxruntime; {model} runs on {runtime}")
        return open_stepper(model, threads=threads, **({"providers": providers} if providers else {}))
    if providers:  # an ONNX graph on "openvino" or "openvino-bf16"
        raise InputError("--providers applies to onnxruntime; OpenVINO runs on its CPU device here")
    from e3dpsm.runtime.openvino_session import OpenVINOStepSession

    return OpenVINOStepSession(model, threads=threads, precision="bf16" if runtime == "openvino-bf16" else "f32")


def resolve_profile(name: str | None, quantization: dict[str, Any] | None, golden_manifest: dict[str, Any],
                    runtime: str = "onnxruntime") -> ToleranceProfile:
    """The named profile (default: the graph's own precision, or bf16 for an fp32 graph run in
    bf16), with the values the golden was recorded for."""
    if name is None:
        name = profile_for_quantization(quantization)
        if runtime == "openvino-bf16" and name == "fp32":
            name = "bf16"
    if name not in PROFILES:
        raise InputError(f"unknown profile {name!r}; choose one of {', '.join(PROFILES)}")
    recorded = golden_manifest.get("tolerances", {}).get(name)
    # A number the golden recorded wins; one it predates (the growth floor) is today's.
    return ToleranceProfile.from_dict({**PROFILES[name].to_dict(), **recorded}) if recorded else PROFILES[name]


def resolve_budget(quantization: dict[str, Any] | None, budget_pct: float | None = None) -> Any:
    """The task budget a compressed graph is held to: `budget_pct` for MPJPE and PA-MPJPE where
    given, else the budget its metadata carries (`quantize` writes it), else the default."""
    from dataclasses import replace

    from e3dpsm.budget import TaskBudget

    fields = dict((quantization or {}).get("budget") or {})
    budget = TaskBudget(**{k: v for k, v in fields.items() if k in TaskBudget.__dataclass_fields__})
    return budget if budget_pct is None else replace(budget, mpjpe_pct=budget_pct, pa_mpjpe_pct=budget_pct)


def isa_comparison(quantization: dict[str, Any] | None) -> dict[str, Any]:
    """The ISA this check runs on beside the one the graph's budget was checked on
    (`quantize` records it): INT8 error differs between AVX2 and VNNI/AMX hosts."""
    from e3dpsm.utils.isa import detect_isa

    host = detect_isa().to_dict()
    checked = (quantization or {}).get("checked_on_isa")
    same = None if not checked else checked.get("kind") == host["kind"]
    return {"host": host, "budget_checked_on": checked, "same_kind": same}


def runtime_comparison(quantization: dict[str, Any] | None, runtime: str) -> dict[str, Any]:
    """The runtime this check runs on beside those the graph's budget was checked on
    (`quantize --runtimes` records them): the same INT8 graph was 0.7% from fp32 on ONNX
    Runtime and 2.2% on OpenVINO over the same frames (docs/quantize.md). `checked_here` is
    None where the graph carries no budget or predates the record."""
    checked = (quantization or {}).get("checked_on_runtimes")
    return {"runtime": runtime, "budget_checked_on": checked,
            "checked_here": None if not checked else runtime in checked}


def budget_runtime_note(comparison: dict[str, Any]) -> str:
    """One line for a check on a runtime the graph's budget was not checked on ("" otherwise)."""
    if comparison["checked_here"] is not False:
        return ""
    checked, runtime = comparison["budget_checked_on"], comparison["runtime"]
    fix = ("quantize checks budgets in f32 only" if runtime.endswith("-bf16") else
           f"to hold it here, quantize with --runtimes {' '.join([*checked, runtime])}")
    return (f"the graph's budget was checked on {' and '.join(checked)}, not on {runtime}: one quantised "
            f"graph's error differs between runtimes; {fix}")


def verify_graph(model: str | os.PathLike, golden_dir: str | os.PathLike | GoldenRecord, out_dir: str | os.PathLike | None = None, *,
                 runtime: str = "onnxruntime", providers: Sequence[str] | None = None, threads: int | None = None,
                 profile: str | None = None, budget_pct: float | None = None, progress: bool = False,
                 header: dict[str, Any] | None = None) -> tuple[GoldenCheck, dict[str, Any]]:
    """Check `model` against `golden_dir` (a folder, or a record already loaded, so that
    several checks read it once); write `OUT/check.json` and `OUT/check.png` if given."""
    from e3dpsm.golden.record import sha256_file
    from e3dpsm.utils.io import atomic_path, write_json_atomic

    from e3dpsm.golden.host import host_rollout_for, kernel_parity_for
    from e3dpsm.utils.isa import detect_isa

    golden = golden_dir if isinstance(golden_dir, GoldenRecord) else load_golden(golden_dir)
    runtime = artifact_check_runtime(model, runtime)
    runner = open_runner(model, runtime, threads=threads, providers=providers)
    chosen = resolve_profile(profile, runner.meta.quantization, golden.manifest, runtime)
    digest = sha256_file(model) if Path(model).is_file() else None  # .mlpackage: a folder
    host = host_rollout_for(golden, digest, runtime) if chosen.kind == "budget" else None
    result = check_golden(runner, golden, chosen, progress=progress, host=host,
                          budget=resolve_budget(runner.meta.quantization, budget_pct), isa_kind=detect_isa().kind,
                          parity=kernel_parity_for(runner.meta.quantization))
    report = {
        **(header or {}),
        "model": {"path": str(model), "sha256": digest, "variant": runner.meta.config.get("variant"),
                  "quantization": runner.meta.quantization},
        "golden": {"path": str(golden.folder), "source": golden.manifest.get("source"), "steps": golden.steps,
                   "window_ms": golden.manifest.get("window_ms")},
        "runtime": runtime, "providers": list(providers or []),
        "isa": isa_comparison(runner.meta.quantization),
        "budget_runtimes": runtime_comparison(runner.meta.quantization, runtime),
        **result.to_dict(),
    }
    if result.questions["same_as_host"] is False and golden.folder is not None:
        if trace_module(model) is None:
            report["kernel_trace"] = _kernel_trace(golden.folder, digest, threads)
        else:  # a .tflite or .pte: where its codes part, if the golden keeps the host's
            report["code_trace"] = _code_trace(golden.folder, model, digest, threads)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        # A device with numpy and onnxruntime only (an ARM board, the emulated aarch64 root)
        # checks all the same; the plot is a convenience there.
        report["plot"] = PLOT_FILE if importlib.util.find_spec("matplotlib") else None
        if report["plot"]:
            with atomic_path(out / PLOT_FILE) as tmp:
                plot_check(result, tmp, f"{Path(model).name} on {runtime} vs golden ({chosen.name}): "
                                        f"{'PASSED' if result.passed else 'FAILED'}")
        write_json_atomic(out / CHECK_FILE, report)
    return result, report


def _code_trace(golden_folder: Path, model: str | os.PathLike, digest: str | None,
                threads: int | None) -> dict[str, Any] | None:
    from e3dpsm.golden.artifact_trace import run_device

    return run_device(golden_folder, model, digest, threads or 1)


def _kernel_trace(golden_folder: Path, digest: str | None, threads: int | None) -> dict[str, Any] | None:
    """Where this machine departs from the host for this graph, when the golden keeps the
    host's kernel trace of it (`golden record --kernel-trace`); None otherwise."""
    import tempfile

    from e3dpsm.golden.kernel_report import find_trace, run_device

    folder = find_trace(golden_folder, digest)
    if folder is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:  # the golden folder may be read-only on a device
        return run_device(folder, threads or 1, out=Path(tmp) / "trace.json")
