"""Pose-accuracy metrics of the E-3DPSM benchmarks (paper Sec. 5.1, Eqs. 23-24), numpy only.

All arrays are `[N, J, 3]` in millimetres, camera frame; N frames of ONE continuous
sequence (the smoothness metric compares consecutive frames, so callers must not
concatenate sequences before calling `e_smooth`).

- MPJPE: mean Euclidean joint error, **not** root-relative.
- PA-MPJPE: MPJPE after aligning each predicted frame to its ground truth with a
  similarity transform (rotation with reflection fix, isotropic scale, translation).
- e_smooth: mean over t >= 2 (1-based) and joints of
  | ||gt_t - gt_(t-1)|| - ||pred_t - pred_(t-1)|| |.

The optional `visible` argument is a selection mask `[N, J]`: only joints where it is
non-zero count. Occlusion-only metrics pass `visible == 0`. An empty selection gives NaN.
The per-joint error functions (`joint_errors`, `pa_joint_errors`, `smooth_errors`) are
public so that per-joint / per-action tables reuse the same formulas.
"""
from __future__ import annotations

import numpy as np

from e3dpsm.errors import InputError

__all__ = ["joint_errors", "pa_joint_errors", "smooth_errors", "jitter_errors", "procrustes_align",
           "mpjpe", "pa_mpjpe", "e_smooth", "jitter", "masked_mean"]


def _check_pair(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.ndim != 3 or pred.shape[-1] != 3 or pred.shape != gt.shape:
        raise InputError(f"expected pred and gt of equal shape [N, J, 3], got {pred.shape} and {gt.shape}")
    return pred, gt


def _check_mask(visible: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
    if visible is None:
        return None
    mask = np.asarray(visible)
    if mask.shape != shape:
        raise InputError(f"expected a joint mask of shape {list(shape)}, got {list(mask.shape)}")
    return mask != 0


def masked_mean(values: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean of `values` over the entries where `mask` is true (all when None); NaN if none."""
    selected = values if mask is None else values[mask]
    return float(selected.mean()) if selected.size else float("nan")


def joint_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Euclidean error per frame and joint, `[N, J]` mm."""
    pred, gt = _check_pair(pred, gt)
    return np.linalg.norm(pred - gt, axis=-1)


def procrustes_align(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Align each frame of `pred` to `gt` with the least-squares similarity transform.

    Umeyama's closed form: the rotation comes from the SVD of the cross-covariance; when
    the best orthogonal map is a reflection (det < 0) the smallest singular direction is
    flipped so the result is a proper rotation.
    """
    pred, gt = _check_pair(pred, gt)
    mu_p = pred.mean(axis=1, keepdims=True)
    mu_g = gt.mean(axis=1, keepdims=True)
    p = pred - mu_p
    g = gt - mu_g
    cov = np.einsum("nji,njk->nik", g, p)  # [N, 3, 3] = sum_j g_j p_j^T
    u, s, vt = np.linalg.svd(cov)
    sign = np.sign(np.linalg.det(u @ vt))
    sign[sign == 0] = 1.0
    fix = np.ones_like(s)
    fix[:, -1] = sign
    rotation = (u * fix[:, None, :]) @ vt  # R maps centred pred onto centred gt
    var_p = (p ** 2).sum(axis=(1, 2))
    # A frame whose prediction collapses to a point has no defined scale: keep it at zero.
    scale = np.divide((s * fix).sum(axis=1), var_p, out=np.zeros_like(var_p), where=var_p > 0)
    return scale[:, None, None] * np.einsum("nik,njk->nji", rotation, p) + mu_g


def pa_joint_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per frame and joint error after per-frame similarity alignment, `[N, J]` mm."""
    return joint_errors(procrustes_align(pred, gt), gt)


def smooth_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """|speed(gt) - speed(pred)| per joint for frames 2..N, `[N - 1, J]` mm per frame."""
    pred, gt = _check_pair(pred, gt)
    speed_gt = np.linalg.norm(np.diff(gt, axis=0), axis=-1)
    speed_pred = np.linalg.norm(np.diff(pred, axis=0), axis=-1)
    return np.abs(speed_gt - speed_pred)


def jitter_errors(pred: np.ndarray) -> np.ndarray:
    """Norm of each joint's second difference for frames 3..N of one continuous sequence,
    `[N - 2, J]` in mm per frame^2. Needs no ground truth: it measures how much a pose
    stream shakes, which a compressed graph must not raise."""
    pred = np.asarray(pred, dtype=np.float64)
    if pred.ndim != 3 or pred.shape[-1] != 3:
        raise InputError(f"expected poses of shape [N, J, 3], got {pred.shape}")
    return np.linalg.norm(pred[2:] - 2.0 * pred[1:-1] + pred[:-2], axis=-1)


def jitter(pred: np.ndarray) -> float:
    """Mean norm of the second difference of one continuous pose sequence (mm per frame^2)."""
    return masked_mean(jitter_errors(pred))


def mpjpe(pred: np.ndarray, gt: np.ndarray, visible: np.ndarray | None = None) -> float:
    """Mean per-joint position error (mm); `visible` selects the joints that count."""
    errors = joint_errors(pred, gt)
    return masked_mean(errors, _check_mask(visible, errors.shape))


def pa_mpjpe(pred: np.ndarray, gt: np.ndarray, visible: np.ndarray | None = None) -> float:
    """MPJPE after per-frame similarity Procrustes alignment of pred to gt (all joints
    define the alignment; `visible` selects which errors count)."""
    errors = pa_joint_errors(pred, gt)
    return masked_mean(errors, _check_mask(visible, errors.shape))


def e_smooth(pred: np.ndarray, gt: np.ndarray, visible: np.ndarray | None = None) -> float:
    """Smoothness error (mm per frame) of one continuous sequence; `visible` [N, J]
    selects joints by their mask at the later frame of each pair."""
    errors = smooth_errors(pred, gt)
    mask = _check_mask(visible, (errors.shape[0] + 1, errors.shape[1]))
    return masked_mean(errors, None if mask is None else mask[1:])
