"""Held-out streams and how a graph does on them: the search's trials and the final check.

Every graph runs as a continuous stream over each held-out sequence (states carried, never
reset), on the same frames as the fp32 graph, whose outputs are computed once. A graph is
judged by the task budget (budget.py) on every runtime asked for, the worst counting: a QDQ
graph is fused and rounded differently by ONNX Runtime and OpenVINO.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from e3dpsm.data.prepared import PreparedSequence
from e3dpsm.metrics import joint_errors
from e3dpsm.budget import BudgetCheck, TaskBudget, check_budget
from e3dpsm.runtime.stepping import Stepper
from e3dpsm.validation.streams import onnx_stream_outputs


@dataclass(frozen=True)
class HeldOut:
    """Frames with ground truth, per sequence, and the fp32 graph's outputs on them."""

    name: str                                   # where the frames come from, for the report
    lnes: tuple[np.ndarray, ...]
    gt: tuple[np.ndarray, ...]
    fp32: tuple[Mapping[str, np.ndarray], ...]  # every pose output of the fp32 graph
    window_ms: float

    @property
    def frames(self) -> int:
        return sum(len(g) for g in self.gt)

    @property
    def fp32_mpjpe(self) -> float:
        return float(np.concatenate([joint_errors(o["pose"], g) for o, g in zip(self.fp32, self.gt)]).mean())

    def head(self, frames: int) -> "HeldOut":
        """The first `frames` of every sequence. The streams are causal, so fp32's outputs on a
        sequence's head are the head of its outputs: nothing is run again."""
        if frames < 1:
            raise ValueError(f"frames must be positive, got {frames}")
        return HeldOut(f"{self.name}[:{frames}]", tuple(x[:frames] for x in self.lnes),
                       tuple(g[:frames] for g in self.gt),
                       tuple({k: v[:frames] for k, v in o.items()} for o in self.fp32), self.window_ms)


EDGE_RUNTIMES = ("executorch", "litert")  # .pte, .tflite: opened by extension (runtime/stepping.py)


def open_stepper(model: str | os.PathLike, runtime: str, threads: int | None) -> Stepper:
    """A session of `model` on `runtime`: ONNX Runtime, OpenVINO's CPU device in f32 (its
    run-time 8-bit quantisation of activations off: runtime/openvino_session.compile_config),
    or an edge artifact's own runtime (ExecuTorch for .pte, LiteRT for .tflite)."""
    if runtime in EDGE_RUNTIMES:
        from e3dpsm.runtime.stepping import artifact_runtime, open_stepper as open_artifact

        if artifact_runtime(model) != runtime:
            raise ValueError(f"{model} is not run by {runtime}; it is a {artifact_runtime(model)} artifact")
        return open_artifact(model, threads=threads)
    if runtime == "openvino":
        from e3dpsm.runtime.openvino_session import OpenVINOStepSession

        return OpenVINOStepSession(model, threads=threads, precision="f32")
    if runtime == "onnxruntime":
        from e3dpsm.runtime import StepSession

        return StepSession(model, threads=threads)
    raise ValueError(f"unknown runtime {runtime!r}; choose onnxruntime, openvino or one of {EDGE_RUNTIMES}")


def held_out(fp32_model: str | os.PathLike, sequences: Sequence[PreparedSequence], window_ms: float,
             frames_per_sequence: int, name: str, threads: int | None = None) -> HeldOut:
    """`frames_per_sequence` frames (0: all) of each sequence, with fp32's outputs on ONNX Runtime."""
    count = None if frames_per_sequence == 0 else frames_per_sequence
    lnes = tuple(np.asarray(s.lnes[:count], dtype=np.float32) for s in sequences)
    gt = tuple(np.asarray(s.j3d_mm[:count], dtype=np.float32) for s in sequences)
    session = open_stepper(fp32_model, "onnxruntime", threads)
    return HeldOut(name, lnes, gt, tuple(onnx_stream_outputs(session, x, window_ms) for x in lnes), window_ms)


def graph_outputs(model: Any, held: HeldOut, runtime: str = "onnxruntime", threads: int | None = None) -> list[dict]:
    return stepper_outputs(open_stepper(model, runtime, threads), held)


def stepper_outputs(stepper: Stepper, held: HeldOut) -> list[dict[str, np.ndarray]]:
    """Every output of `stepper` streamed over each held-out sequence, states carried."""
    return [onnx_stream_outputs(stepper, x, held.window_ms) for x in held.lnes]


def check_stepper(stepper: Stepper, held: HeldOut, budget: TaskBudget) -> BudgetCheck:
    """The task budget of an opened stepper on `held`, against fp32 on ONNX Runtime."""
    return check_budget([o["pose"] for o in stepper_outputs(stepper, held)], [o["pose"] for o in held.fp32],
                        list(held.gt), budget)


def distance_pct(outputs: Sequence[Mapping[str, np.ndarray]], held: HeldOut) -> float:
    """The mean joint distance of the fused poses to fp32's, in % of fp32's MPJPE: a fidelity
    figure (and the smooth, low-noise measure the search ranks nodes by)."""
    distance = np.concatenate([joint_errors(o["pose"], f["pose"]).ravel() for o, f in zip(outputs, held.fp32)])
    return float(100.0 * distance.mean() / held.fp32_mpjpe)


@dataclass(frozen=True)
class Judgement:
    """A graph's task budget on held-out frames on each runtime; the worst runtime counts."""

    by_runtime: Mapping[str, BudgetCheck]

    @property
    def worst(self) -> BudgetCheck:
        return max(self.by_runtime.values(), key=lambda check: check.worst_share)

    @property
    def within(self) -> bool:
        return all(check.within for check in self.by_runtime.values())

    @property
    def worst_share(self) -> float:
        return self.worst.worst_share

    @property
    def fidelity_pct(self) -> float:
        return max(check.fidelity_pct for check in self.by_runtime.values())

    def to_dict(self) -> dict:
        return {"within": self.within, "by_runtime": {r: c.to_dict() for r, c in self.by_runtime.items()}}


def judge(model: str | os.PathLike, held: HeldOut, budget: TaskBudget, runtimes: Sequence[str],
          threads: int | None = None) -> Judgement:
    """The task budget of `model` on `held` on each of `runtimes`, against fp32 on ONNX Runtime
    (the reference every runtime's graph is held to)."""
    return Judgement({runtime: check_stepper(open_stepper(model, runtime, threads), held, budget)
                      for runtime in runtimes})
