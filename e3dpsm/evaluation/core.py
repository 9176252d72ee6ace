"""Benchmark figures from per-frame predictions (torch-free; used by `e3dpsm evaluate` for
PyTorch models and by `validate` for ONNX predictions).

Conventions (paper Sec. 5.1, Table 13; docs/model.md#citations, Benchmark totals): totals
are the unweighted mean of the per-action means
(frames with action -1 form an "unknown" group); occlusion-only figures count the joints
with visible == 0; e_smooth pairs consecutive frames of the same sequence only, and a pair
belongs to the action (and joint mask) of its later frame. Per-joint figures and
"frame_weighted" are plain means over all frames.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from e3dpsm.errors import InputError
from e3dpsm.joints import JOINT_NAMES
from e3dpsm.metrics import joint_errors, masked_mean, pa_joint_errors, smooth_errors

UNKNOWN_ACTION = "unknown"
METRICS = ("mpjpe", "pa_mpjpe", "e_smooth", "mpjpe_occluded", "pa_mpjpe_occluded")
TIME_BINS = 10


def _smooth_per_frame(pred: np.ndarray, gt: np.ndarray, sequence_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[N, J] smoothness error at each frame's pair with its predecessor, and [N] validity
    (false on the first frame of every sequence)."""
    errors = np.zeros(gt.shape[:2])
    valid = np.zeros(gt.shape[0], dtype=bool)
    for sid in np.unique(sequence_ids):
        idx = np.flatnonzero(sequence_ids == sid)
        if idx.size > 1:
            errors[idx[1:]] = smooth_errors(pred[idx], gt[idx])
            valid[idx[1:]] = True
    return errors, valid


def _figures(err: np.ndarray, pa_err: np.ndarray, smooth: np.ndarray, smooth_valid: np.ndarray,
             occluded: np.ndarray, frames: np.ndarray) -> dict[str, float]:
    """The five metrics over the frames selected by the boolean [N] `frames`."""
    sel_smooth = frames & smooth_valid
    return {
        "mpjpe": masked_mean(err[frames]),
        "pa_mpjpe": masked_mean(pa_err[frames]),
        "e_smooth": masked_mean(smooth[sel_smooth]),
        "mpjpe_occluded": masked_mean(err[frames], occluded[frames]),
        "pa_mpjpe_occluded": masked_mean(pa_err[frames], occluded[frames]),
        "frames": int(frames.sum()),
    }


def _error_over_time(err: np.ndarray, sequence_ids: np.ndarray) -> dict[str, list[float]]:
    """Mean MPJPE in TIME_BINS equal parts of every sequence (drift shows as a rising curve)."""
    sums, counts = np.zeros(TIME_BINS), np.zeros(TIME_BINS)
    for sid in np.unique(sequence_ids):
        per_frame = err[sequence_ids == sid].mean(axis=1)
        bins = np.minimum((np.arange(per_frame.size) * TIME_BINS) // per_frame.size, TIME_BINS - 1)
        np.add.at(sums, bins, per_frame)
        np.add.at(counts, bins, 1)
    means = np.divide(sums, counts, out=np.full(TIME_BINS, np.nan), where=counts > 0)
    return {"bin_centres": [(i + 0.5) / TIME_BINS for i in range(TIME_BINS)], "mpjpe": means.tolist()}


def evaluate_predictions(pred_mm: np.ndarray, gt_mm: np.ndarray, visible: np.ndarray, action: np.ndarray,
                         action_names: Sequence[str], sequence_ids: np.ndarray,
                         sequence_names: Sequence[str] | None = None) -> dict[str, Any]:
    """All benchmark figures (JSON-ready) of predictions [N, J, 3] mm against ground truth."""
    pred, gt = np.asarray(pred_mm, np.float64), np.asarray(gt_mm, np.float64)
    n = gt.shape[0]
    visible, action, sequence_ids = np.asarray(visible), np.asarray(action), np.asarray(sequence_ids)
    if visible.shape != gt.shape[:2] or action.shape != (n,) or sequence_ids.shape != (n,):
        raise InputError(f"visible {visible.shape}, action {action.shape}, sequence_ids {sequence_ids.shape} "
                         f"do not match {n} frames of {gt.shape[1]} joints")
    err, pa_err = joint_errors(pred, gt), pa_joint_errors(pred, gt)
    smooth, smooth_valid = _smooth_per_frame(pred, gt, sequence_ids)
    occluded = visible == 0
    everything = np.ones(n, dtype=bool)

    per_action: dict[str, dict[str, float]] = {}
    for label in np.unique(action):
        name = action_names[label] if 0 <= label < len(action_names) else UNKNOWN_ACTION
        per_action[name] = _figures(err, pa_err, smooth, smooth_valid, occluded, action == label)
    totals = {m: _nanmean([row[m] for row in per_action.values()]) for m in METRICS}

    joint_names = JOINT_NAMES if gt.shape[1] == len(JOINT_NAMES) else [str(j) for j in range(gt.shape[1])]
    per_joint = {
        name: {"mpjpe": masked_mean(err[:, j]), "pa_mpjpe": masked_mean(pa_err[:, j]),
               "e_smooth": masked_mean(smooth[smooth_valid, j]), "mpjpe_occluded": masked_mean(err[:, j], occluded[:, j])}
        for j, name in enumerate(joint_names)
    }
    per_sequence = {
        (sequence_names[int(sid)] if sequence_names is not None else str(sid)):
            _figures(err, pa_err, smooth, smooth_valid, occluded, sequence_ids == sid)
        for sid in np.unique(sequence_ids)
    }
    return {
        "frames": n,
        "totals": totals,
        "frame_weighted": _figures(err, pa_err, smooth, smooth_valid, occluded, everything),
        "per_action": per_action,
        "per_joint": per_joint,
        "per_sequence": per_sequence,
        "error_over_time": _error_over_time(err, sequence_ids),
    }


def per_frame_mpjpe(pred_mm: np.ndarray, gt_mm: np.ndarray) -> np.ndarray:
    """[N] mean joint error of each frame (for error-along-the-sequence plots)."""
    return joint_errors(pred_mm, gt_mm).mean(axis=1)


def _nanmean(values: list[float]) -> float:
    finite = [v for v in values if not np.isnan(v)]
    return float(np.mean(finite)) if finite else float("nan")
