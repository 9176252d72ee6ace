"""Pose fusion of the direct pose (observation) and the delta pose (motion update).

Learned Kalman fusion (paper Sec. 4.2, Eqs. 12-16): state X (the pose, 48 values) and
covariance Sigma, A = B = H = I, learned constant Q and R. With diagonal Q, R and P0 = I
every matrix in the filter stays diagonal, so the filter is exact in element-wise form: no
matrix inverse, which ONNX lacks (docs/model.md#citations, Kalman fusion). Covariances are
carried per coordinate, [J, 3].

Modes (the paper's ablations):
- "learned": Kalman filter with learned log Q, log R (init Q = 1e-3, R = 1e-2, poses in mm);
- "static":  the same filter with Q, R fixed at their initial values;
- "naive":   previous fused pose + delta (drifts: errors accumulate). The paper's equation
             adds the delta to the previous *direct* pose; its ablation text speaks of delta
             accumulation, which is what is built here;
- "direct":  the direct pose alone.

First step of a stream (per-stream flag `initialised` = 0): output the direct pose and start
the filter from it with covariance P0. The flag lives in the state, so callers need no
special first call.
"""
from __future__ import annotations

import math
from typing import Literal

import torch
from torch import nn

FusionMode = Literal["learned", "static", "naive", "direct"]
FUSION_MODES: tuple[str, ...] = ("learned", "static", "naive", "direct")


class PoseFusion(nn.Module):
    def __init__(
        self, num_joints: int, mode: FusionMode = "learned", q_init: float = 1e-3, r_init: float = 1e-2,
        p0: float = 1.0,
    ) -> None:
        super().__init__()
        if mode not in FUSION_MODES:
            raise ValueError(f"unknown fusion mode {mode!r}; choose from {FUSION_MODES}")
        self.mode, self.p0 = mode, p0
        log_q = torch.full((num_joints, 3), math.log(q_init))
        log_r = torch.full((num_joints, 3), math.log(r_init))
        if mode == "learned":
            self.log_q, self.log_r = nn.Parameter(log_q), nn.Parameter(log_r)
        else:
            self.register_buffer("log_q", log_q)
            self.register_buffer("log_r", log_r)

    @property
    def uses_covariance(self) -> bool:
        return self.mode in ("learned", "static")

    def forward(
        self,
        direct: torch.Tensor,
        delta: torch.Tensor,
        prev_pose: torch.Tensor,
        prev_cov: torch.Tensor | None,
        initialised: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """direct, delta, prev_pose: [B, J, 3] (mm); prev_cov [B, J, 3] or None;
        initialised: [B, 1]. Returns (fused pose, new covariance or None)."""
        started = initialised.view(-1, 1, 1)
        if self.mode == "direct":
            return direct, None
        predicted = prev_pose + delta
        if self.mode == "naive":
            return started * predicted + (1 - started) * direct, None
        q, r = self.log_q.exp(), self.log_r.exp()
        cov_pred = prev_cov + q
        gain = cov_pred / (cov_pred + r)
        fused = predicted + gain * (direct - predicted)
        # Joseph form, element-wise: (1-K) P (1-K)^T + K R K^T.
        cov = (1 - gain) ** 2 * cov_pred + gain**2 * r
        fused = started * fused + (1 - started) * direct
        cov = started * cov + (1 - started) * torch.full_like(cov, self.p0)
        return fused, cov
