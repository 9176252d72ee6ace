"""Host rollouts: what the host computed for a compressed graph, kept beside the golden record.

`golden check` asks two questions of a compressed graph. Is it accurate enough (its task
budget against the fp32 golden and the ground truth; check.py)? And does this device compute
what the host computed for the same graph? An INT8 graph's rounding is a chaotic function of
its kernels: the committed `small`'s full-integer graph on OpenVINO lands 2.6 mm (mean) and
11.7 mm (max) from the same graph on ONNX Runtime over 600 frames of one host, about as far as
either is from fp32 (2.9 mm), while two thread counts of ONNX Runtime agree to the bit
(docs/golden-and-diagnose.md). So the second question needs the host's own rollout of that
graph on that runtime, recorded here (`golden record --also GRAPH --runtime ...`), and a
tolerance that knows the kernels: tight on the ISA kind the host had, the kernel-parity
tolerance on another (another x86 kind, an ARM board).

    DIR/host/<graph stem>-<sha256[:12]>-<runtime>.npz   out.<name> float32 [N, J, 3] at every step
    (the digest in the name: two graphs of one file name, e.g. two `step_int8.onnx`, keep one each)
    golden.json "host_rollouts": [{file, graph, sha256, runtime, isa, threads}]
"""
from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from e3dpsm.errors import DataError
from e3dpsm.golden.store import MANIFEST_FILE, GoldenRecord, load_golden
from e3dpsm.utils.io import atomic_path, write_json_atomic

HOST_FOLDER = "host"


@dataclass(frozen=True)
class KernelParity:
    """How close a device's outputs must be to the host's rollout of the same graph, in mm
    (mean joint distance: over the rollout, and at any one step)."""

    same_kind_mean_mm: float = 0.01   # the host's own ISA kind and runtime: the same kernels
    same_kind_step_mm: float = 0.1
    other_kind_mean_mm: float = 0.5   # another ISA kind: other integer kernels, other rounding
    other_kind_step_mm: float = 5.0

    def limits(self, same_kind: bool) -> tuple[float, float]:
        """(mean limit, step limit) for a device of the host's ISA kind or another."""
        if same_kind:
            return self.same_kind_mean_mm, self.same_kind_step_mm
        return self.other_kind_mean_mm, self.other_kind_step_mm


# Quantisation modes whose arithmetic is float (weights stored in 8 bits, dequantised before
# every operator: export/litert_weights8.py): nothing is rounded to a code at run time, so
# another ISA's kernels differ from the host's in the last bits only, as fp32 artifacts do
# (2.4e-4 mm under emulated aarch64), and the same-kind tolerance holds on any ISA.
FLOAT_ARITHMETIC_MODES = ("int8-weights",)


def kernel_parity_for(quantization: Mapping[str, Any] | None) -> KernelParity:
    """The kernel-parity tolerance a graph of this quantisation is held to on another ISA."""
    parity = KernelParity()
    if (quantization or {}).get("mode") in FLOAT_ARITHMETIC_MODES:
        return replace(parity, other_kind_mean_mm=parity.same_kind_mean_mm, other_kind_step_mm=parity.same_kind_step_mm)
    return parity


@dataclass(frozen=True)
class HostRollout:
    entry: Mapping[str, Any]             # the manifest's record of it
    outputs: Mapping[str, np.ndarray]    # output name -> [N, J, 3]

    def same_kind(self, isa_kind: str) -> bool:
        return (self.entry.get("isa") or {}).get("kind") == isa_kind


def record_host_rollouts(golden_dir: str | os.PathLike, models: Sequence[str | os.PathLike],
                         runtimes: Sequence[str], threads: int | None = None) -> list[dict[str, Any]]:
    """Step each of `models` on each of `runtimes` over the golden's frames, states carried, and
    keep its outputs; the manifest lists them (replacing earlier rollouts of the same graph
    and runtime). Returns the new entries."""
    from e3dpsm.golden.record import sha256_file
    from e3dpsm.golden.verify import open_runner
    from e3dpsm.runtime.stepping import artifact_runtime
    from e3dpsm.utils.isa import detect_isa

    golden = load_golden(golden_dir)
    folder = Path(golden_dir) / HOST_FOLDER
    folder.mkdir(exist_ok=True)
    entries = []
    for model in models:
        digest = sha256_file(model)
        # A .tflite or .pte runs on its own runtime whatever `runtimes` says, and `golden
        # check` looks its rollout up under that name.
        own = artifact_runtime(model)
        for runtime in (runtimes if own == "onnxruntime" else [own]):
            runner = open_runner(model, runtime, threads=threads)
            outputs = _rollout(runner, golden)
            name = f"{Path(model).stem}-{digest[:12]}-{runtime}.npz"
            with atomic_path(folder / name, suffix=".npz") as tmp:
                np.savez_compressed(tmp, **{f"out.{k}": v for k, v in outputs.items()})
            entries.append({"file": f"{HOST_FOLDER}/{name}", "graph": Path(model).name, "sha256": digest,
                            "runtime": runtime, "isa": detect_isa().to_dict(), "threads": threads})
    replaced = {(e["sha256"], e["runtime"]) for e in entries}
    kept = [e for e in golden.manifest.get("host_rollouts", []) if (e["sha256"], e["runtime"]) not in replaced]
    write_json_atomic(Path(golden_dir) / MANIFEST_FILE, {**golden.manifest, "host_rollouts": kept + entries})
    return entries


def _rollout(runner: Any, golden: GoldenRecord) -> dict[str, np.ndarray]:
    state = runner.init_state(1)
    steps: list[dict[str, np.ndarray]] = []
    for step in range(golden.steps):
        outputs, state = runner.step(golden.frame(step), state, golden.window_ms(step))
        steps.append({name: np.asarray(outputs[name], dtype=np.float32)[0] for name in golden.output_names})
    return {name: np.stack([s[name] for s in steps]) for name in golden.output_names}


def host_rollout_for(golden: GoldenRecord, sha256: str, runtime: str) -> HostRollout | None:
    """The host's rollout of the graph with this digest on this runtime, if the golden holds one."""
    entry = next((e for e in golden.manifest.get("host_rollouts", [])
                  if e.get("sha256") == sha256 and e.get("runtime") == runtime), None)
    if entry is None or golden.folder is None:
        return None
    from e3dpsm.data.formats.npz import load_arrays

    path = golden.folder / entry["file"]
    if not path.is_file():
        raise DataError(f"{path}: the host rollout the manifest lists is missing; record it again with golden record --also")
    arrays = load_arrays(path, tuple(f"out.{name}" for name in golden.output_names), ndim=3, what="the host rollout")
    outputs = {name: arrays[f"out.{name}"] for name in golden.output_names}
    if any(v.shape[0] != golden.steps for v in outputs.values()):
        raise DataError(f"{path} does not hold the golden's {golden.steps} steps; record it again")
    return HostRollout(entry, outputs)
