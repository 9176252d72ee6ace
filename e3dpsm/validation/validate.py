"""Validate model variants side by side on held-out sequences, run as continuous streams.

Each variant (the PyTorch checkpoint if given, every ONNX graph) predicts every held-out
sequence from its initial state with states carried; the metrics are the benchmark's
(e3dpsm.metrics) pooled over all frames, e_smooth per sequence then frame-weighted. The
reference for differences is the first ONNX graph whose metadata has no quantisation.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from e3dpsm.data.prepared import PreparedData, PreparedSequence
from e3dpsm.errors import ConfigError, InputError
from e3dpsm.joints import JOINT_NAMES
from e3dpsm.metrics import e_smooth, joint_errors, masked_mean, pa_mpjpe
from e3dpsm.runtime.stepping import GraphStepper, open_stepper
from e3dpsm.validation.streams import onnx_stream, torch_stream

log = logging.getLogger(__name__)


@dataclass
class Variant:
    label: str
    kind: str                      # "pytorch" | "onnx"
    precision: str                 # fp32, fp16, int8, int8-dynamic
    path: str
    poses: list[np.ndarray] = field(default_factory=list)  # per sequence [F, 16, 3]


@dataclass
class ValidationResult:
    rows: list[dict[str, Any]]       # one per variant: metrics and differences to the reference
    per_joint: dict[str, list[float]]  # label -> MPJPE per joint
    reference: str
    frames: int
    sequences: list[str]

    def to_dict(self) -> dict[str, Any]:
        return {"reference": self.reference, "frames": self.frames, "sequences": self.sequences,
                "rows": self.rows, "per_joint_mpjpe_mm": self.per_joint, "joints": list(JOINT_NAMES)}


def variant_metrics(poses: Sequence[np.ndarray], seqs: Sequence[PreparedSequence], frames: int) -> dict[str, Any]:
    pred = np.concatenate(poses)
    gt = np.concatenate([np.asarray(s.j3d_mm[:frames], np.float32) for s in seqs])
    visible = np.concatenate([np.asarray(s.visible[:frames]) for s in seqs])
    errors = joint_errors(pred, gt)
    smooth = [(e_smooth(p, np.asarray(s.j3d_mm[:frames], np.float32)), len(p)) for p, s in zip(poses, seqs) if len(p) > 1]
    return {
        "mpjpe_mm": masked_mean(errors),
        "pa_mpjpe_mm": pa_mpjpe(pred, gt),
        "e_smooth_mm": float(np.average([v for v, _ in smooth], weights=[n for _, n in smooth])) if smooth else float("nan"),
        "occluded_mpjpe_mm": masked_mean(errors, visible == 0),
        "occluded_joints": int(np.count_nonzero(visible == 0)),
        "per_joint_mm": errors.mean(axis=0).tolist(),
    }


def _onnx_variant(path: str | os.PathLike, threads: int | None) -> tuple[Variant, GraphStepper]:
    session = open_stepper(path, threads=threads)
    quant = session.meta.quantization
    precision = "fp32" if quant is None else str(quant.get("mode", "quantised"))
    return Variant(f"{Path(path).stem} ({precision})", "onnx", precision, str(path)), session


def validate_variants(
    models: Sequence[str | os.PathLike], data_dir: str | os.PathLike, *, checkpoint: str | os.PathLike | None = None,
    split: str = "test", window_ms: float | None = None, frames: int | None = None, threads: int | None = None,
) -> ValidationResult:
    if not models:
        raise ConfigError("give at least one ONNX model (--models A.onnx ...)")
    data = PreparedData.open(data_dir)
    window = float(window_ms or data.window_ms)
    data.check_compatible(window_ms=window)
    seqs = data.split(split)
    limit = min(s.frames for s in seqs) if frames is None else int(frames)
    if limit < 2:
        raise InputError(f"--frames must be at least 2 (e_smooth compares consecutive frames), got {limit}")

    variants: list[Variant] = []
    if checkpoint is not None:
        from e3dpsm.checkpoint import load_checkpoint

        model, _ = load_checkpoint(checkpoint)
        data.check_compatible(height=model.config.height, width=model.config.width)
        torch_variant = Variant("pytorch", "pytorch", "fp32", str(checkpoint))
        torch_variant.poses = [torch_stream(model, s.lnes, window, limit) for s in seqs]
        variants.append(torch_variant)
    for path in models:
        variant, session = _onnx_variant(path, threads)
        height, width = session.meta.frame_hw
        data.check_compatible(height=height, width=width)
        variant.poses = [onnx_stream(session, s.lnes, window, limit) for s in seqs]
        variants.append(variant)
        log.info("%s: %d sequences streamed", variant.label, len(seqs))

    labels = [v.label for v in variants]
    if len(set(labels)) != len(labels):  # the same file name twice: make the labels unique
        for i, v in enumerate(variants):
            v.label = f"{i}:{v.label}"
    onnx_fp32 = [v for v in variants if v.kind == "onnx" and v.precision == "fp32"]
    reference = onnx_fp32[0] if onnx_fp32 else variants[0]
    ref_metrics = variant_metrics(reference.poses, seqs, limit)
    rows, per_joint = [], {}
    for v in variants:
        m = variant_metrics(v.poses, seqs, limit)
        per_joint[v.label] = m.pop("per_joint_mm")
        deviation = joint_errors(np.concatenate(v.poses), np.concatenate(reference.poses)).mean()
        rows.append({
            "variant": v.label, "kind": v.kind, "precision": v.precision, "path": v.path, **m,
            "delta_mpjpe_mm": m["mpjpe_mm"] - ref_metrics["mpjpe_mm"],
            "delta_mpjpe_pct": 100.0 * (m["mpjpe_mm"] - ref_metrics["mpjpe_mm"]) / ref_metrics["mpjpe_mm"],
            "delta_pa_mpjpe_mm": m["pa_mpjpe_mm"] - ref_metrics["pa_mpjpe_mm"],
            "delta_e_smooth_mm": m["e_smooth_mm"] - ref_metrics["e_smooth_mm"],
            "deviation_from_reference_mm": float(deviation),
        })
    return ValidationResult(rows, per_joint, reference.label, limit * len(seqs), [s.name for s in seqs])
