"""Checkpoint + prepared data -> results dict and a report folder (`e3dpsm evaluate`)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from e3dpsm.data.prepared import PreparedData
from e3dpsm.evaluation.core import evaluate_predictions, per_frame_mpjpe
from e3dpsm.evaluation.plots import plot_error_along_sequences, plot_per_joint
from e3dpsm.evaluation.runner import SplitPredictions, predict_split
from e3dpsm.evaluation.tables import results_markdown
from e3dpsm.utils.io import atomic_dir, write_json_atomic, write_text_atomic

DEFAULT_CHUNK = 40  # causal chunk length, and the non-causal window when a run lacks one


def evaluate_checkpoint(checkpoint: str | os.PathLike, data: PreparedData, split: str, causal: bool,
                        window_ms: float | None = None, progress: bool = False) -> tuple[dict[str, Any], SplitPredictions]:
    """Load a checkpoint, predict the split, compute every figure."""
    from e3dpsm.checkpoint import load_checkpoint

    model, payload = load_checkpoint(checkpoint)
    data.check_compatible(window_ms=window_ms, height=model.config.height, width=model.config.width)
    seq_len = int(payload.get("train_args", {}).get("seq_len", DEFAULT_CHUNK))
    sequences = data.split(split)
    preds = predict_split(model, sequences, causal, data.window_ms, chunk=DEFAULT_CHUNK if causal else seq_len,
                          progress=progress)
    results = evaluate_predictions(preds.pred_mm, preds.gt_mm, preds.visible, preds.action, data.action_names,
                                   preds.sequence_ids, preds.sequence_names)
    results["direct_head"] = evaluate_predictions(preds.pred_direct_mm, preds.gt_mm, preds.visible, preds.action,
                                                  data.action_names, preds.sequence_ids, preds.sequence_names)["totals"]
    results["model"] = {"variant": model.config.variant, "fusion": model.config.fusion,
                        "ssm_stages": list(model.config.ssm_stages), "train_step": payload.get("step"),
                        "train_window_ms": model.config.train_window_ms}
    results["mode"] = "causal" if causal else f"non-causal (windows of {seq_len} frames)"
    return results, preds


def write_report(out: str | os.PathLike, header: dict[str, Any], results: dict[str, Any], preds: SplitPredictions,
                 window_ms: float, force: bool = False) -> Path:
    """OUT/metrics.json, OUT/metrics.md, OUT/predictions.npz, OUT/error_along_sequences.png,
    OUT/per_joint.png; built under a temporary name, renamed when complete."""
    with atomic_dir(out, force=force) as tmp:
        write_json_atomic(tmp / "metrics.json", {**header, **results})
        write_text_atomic(tmp / "metrics.md", results_markdown(results, f"Evaluation: {results['mode']}"))
        np.savez_compressed(tmp / "predictions.npz", pred_mm=preds.pred_mm, gt_mm=preds.gt_mm,
                            sequence_ids=preds.sequence_ids)
        per_frame = {name: per_frame_mpjpe(preds.pred_mm[preds.sequence_ids == i], preds.gt_mm[preds.sequence_ids == i])
                     for i, name in enumerate(preds.sequence_names)}
        plot_error_along_sequences(per_frame, window_ms, tmp / "error_along_sequences.png")
        plot_per_joint(results["per_joint"], tmp / "per_joint.png")
    return Path(out)
