"""The paper's training objective (section "Loss Functions"), poses in millimetres:

    L = w_3d L_3D + w_delta L_delta + w_2d L_2D + w_bl L_BL + w_ba L_BA

- L_3D: mean squared joint error (mm^2);
- L_delta: mean squared error of the predicted delta pose against the ground-truth
  inter-frame displacement P_t - P_(t-1), for t >= 2 of each window;
- L_2D: mean squared error (frame px^2) of the predicted joints projected through the
  fisheye camera against the 2D ground truth; joints whose ground truth lies outside the
  field of view are skipped (their projection is clamped, hence meaningless), and with
  `mask_invisible` occluded joints too;
- L_BL: L1 on the lengths of the LIMB_PAIRS bones;
- L_BA: cosine distance between predicted and ground-truth LIMB_PAIRS bone vectors.

Which output gets which term (our choice, stated in `PoseLoss`): the pose terms (3D, 2D,
bones) supervise the fused `pose` as in the paper AND `pose_direct`, because the Kalman
fusion is only as good as the measurement it corrects with; the delta term supervises
`pose_delta`.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from e3dpsm.joints import LIMB_PAIRS
from e3dpsm.training.projection import FisheyeProjection

_LIMB_INDEX = torch.tensor(LIMB_PAIRS, dtype=torch.long)


@dataclass(frozen=True)
class LossWeights:
    """Paper defaults (the released code uses 0.02 for 3D)."""

    pose_3d: float = 0.01
    delta: float = 0.01
    pose_2d: float = 0.01
    bone_length: float = 1e-3
    bone_angle: float = 1e-3

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def bone_vectors(pose: torch.Tensor) -> torch.Tensor:
    """[..., J, 3] -> [..., len(LIMB_PAIRS), 3], child minus parent of each limb bone."""
    index = _LIMB_INDEX.to(pose.device)
    return pose[..., index[:, 1], :] - pose[..., index[:, 0], :]


def _masked_mean(values: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if mask is None:
        return values.mean()
    mask = mask.to(values.dtype)
    return (values * mask).sum() / mask.sum().clamp_min(1.0)


def pose_3d_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    return ((pred - gt) ** 2).sum(-1).mean()


def delta_loss(delta: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """delta, gt: [B, T, J, 3]; the first frame of a window has no ground-truth delta."""
    return ((delta[:, 1:] - (gt[:, 1:] - gt[:, :-1])) ** 2).sum(-1).mean()


def bone_length_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    return (bone_vectors(pred).norm(dim=-1) - bone_vectors(gt).norm(dim=-1)).abs().mean()


def bone_angle_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    cosine = nn.functional.cosine_similarity(bone_vectors(pred), bone_vectors(gt), dim=-1, eps=1e-6)
    return (1.0 - cosine).mean()


class PoseLoss(nn.Module):
    """Weighted sum of the five terms; `forward` returns (total, {term: value}) where the
    term values are unweighted (for logging)."""

    def __init__(self, projection: FisheyeProjection, weights: LossWeights = LossWeights(),
                 supervise_direct: bool = True, mask_invisible: bool = False) -> None:
        super().__init__()
        self.projection = projection
        self.weights = weights
        self.supervise_direct = supervise_direct
        self.mask_invisible = mask_invisible

    def _pose_terms(self, pred: torch.Tensor, gt_mm: torch.Tensor, gt_px: torch.Tensor,
                    mask_2d: torch.Tensor) -> dict[str, torch.Tensor]:
        pred_px = self.projection(pred / 1000.0)
        return {
            "pose_3d": pose_3d_loss(pred, gt_mm),
            "pose_2d": _masked_mean(((pred_px - gt_px) ** 2).sum(-1), mask_2d),
            "bone_length": bone_length_loss(pred, gt_mm),
            "bone_angle": bone_angle_loss(pred, gt_mm),
        }

    def forward(self, outputs: dict[str, torch.Tensor], j3d_mm: torch.Tensor, j2d_px: torch.Tensor,
                visible: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        mask_2d = self.projection.in_fov(j3d_mm / 1000.0)
        if self.mask_invisible:
            mask_2d = mask_2d & (visible > 0)
        heads = ["pose", "pose_direct"] if self.supervise_direct else ["pose"]
        terms: dict[str, torch.Tensor] = {}
        for head in heads:
            for name, value in self._pose_terms(outputs[head], j3d_mm, j2d_px, mask_2d).items():
                terms[name] = terms.get(name, 0.0) + value / len(heads)
        terms["delta"] = delta_loss(outputs["pose_delta"], j3d_mm)
        w = self.weights
        total = (w.pose_3d * terms["pose_3d"] + w.delta * terms["delta"] + w.pose_2d * terms["pose_2d"]
                 + w.bone_length * terms["bone_length"] + w.bone_angle * terms["bone_angle"])
        return total, terms
