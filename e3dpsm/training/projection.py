"""Differentiable fisheye projection for the 2D loss: the torch twin of
`e3dpsm.camera.OcamCamera.project`, with the same convention (x right, y down, z along the
optical axis into the scene; u column, v row in sensor pixels; no flip) and the same steps
(invpol guess, one Newton step on pol, field-of-view clamp), so a loss computed here agrees
with the 2D ground truth the data pipeline produced with the numpy camera.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from e3dpsm.camera import OcamCamera

# Added to n^2 so the direction x / n has a finite gradient on the optical axis, where
# rho -> 0 makes the direction irrelevant anyway. 1e-12 m^2 moves no point by > 1e-6 px.
_AXIS_EPS_M2 = 1e-12


def _polyval(coeffs: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Ascending coefficients, Horner's rule."""
    out = torch.zeros_like(x)
    for c in coeffs.flip(0):
        out = out * x + c
    return out


class FisheyeProjection(nn.Module):
    """Camera-frame points [..., 3] in metres -> pixels [..., 2], scaled by `pixel_scale`
    (sensor -> network frame, 0.4 for 640x480 -> 256x192)."""

    def __init__(self, camera: OcamCamera, pixel_scale: float = 1.0) -> None:
        super().__init__()
        as_tensor = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
        pol = np.asarray(camera.pol, dtype=np.float64)
        self.register_buffer("pol", as_tensor(pol), persistent=False)
        self.register_buffer("d_pol", as_tensor(np.polynomial.polynomial.polyder(pol)), persistent=False)
        self.register_buffer("invpol", as_tensor(camera.invpol), persistent=False)
        self.centre = (camera.xc, camera.yc)
        self.affine = (camera.c, camera.d, camera.e)
        self.theta_min = camera.theta_min
        self.pixel_scale = float(pixel_scale)

    def in_fov(self, points_m: torch.Tensor) -> torch.Tensor:
        """True where a ray lies inside the field of view the projection covers."""
        n = torch.hypot(points_m[..., 0], points_m[..., 1])
        return torch.atan2(points_m[..., 2], n) >= self.theta_min

    def forward(self, points_m: torch.Tensor) -> torch.Tensor:
        dtype = points_m.dtype
        pts = points_m.to(self.pol.dtype)  # float64: the degree-8 invpol loses digits in float32
        x, y, z = pts.unbind(-1)
        n = torch.sqrt(x * x + y * y + _AXIS_EPS_M2)
        theta = torch.atan2(z, n).clamp(self.theta_min, math.pi / 2)
        rho = _polyval(self.invpol, theta)
        cos_t, sin_t = torch.cos(theta), torch.sin(theta)
        residual = _polyval(self.pol, rho) * cos_t - rho * sin_t
        slope = _polyval(self.d_pol, rho) * cos_t - sin_t
        rho = (rho - residual / slope).clamp_min(0.0)
        px, py = x / n * rho, y / n * rho
        c, d, e = self.affine
        u = self.centre[0] + px * c + py * d
        v = self.centre[1] + px * e + py
        return (torch.stack([u, v], dim=-1) * self.pixel_scale).to(dtype)
