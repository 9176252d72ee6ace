"""Scaramuzza omnidirectional ("OCamCalib") camera model of the EE3D head-mounted fisheye.

Convention (used everywhere in e3dpsm, including the synthetic data):

* Camera frame: x to the right of the image (growing u), y down the image (growing v),
  z along the optical axis, *out of* the lens into the scene. A head-mounted camera tilted
  down therefore has the wearer's body at positive z.
* Pixels: u is the column, v the row, both in sensor pixels of the 640 x 480 image,
  (0, 0) the centre of the top-left pixel. No v flip.
* Projection (Scaramuzza's omnidirectional model: paper Sec. 4.3, Eq. 19, and
  docs/model.md#citations, Fisheye camera): with n = sqrt(x^2 + y^2) and
  theta = atan2(z, n) (the elevation of the ray above the image plane; pi/2 on the
  optical axis),
  rho = invpol(theta) and
      u = xc + (x/n) rho c + (y/n) rho d,   v = yc + (x/n) rho e + (y/n) rho.
  Back-projection inverts the affine part and lifts the pixel to the ray
  (px, py, pol(rho)). The public EE3D `pol` has a positive constant term, which is what
  makes z point into the scene; the EventEgo3D code reaches the same place by negating z
  and flipping v, which this module does not need.

`invpol` is not published; `ee3d_default()` fits it from `pol` by least squares over the
angles the image rectangle spans, as OCamCalib's own calibration toolbox does.
Numpy only: the runtime and data code use this module without torch.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from e3dpsm.errors import InputError

# Public calibration of the EE3D head-mounted camera, rounded (EventEgo3D++'s intrinsics.json:
# docs/model.md#citations, Fisheye camera).
EE3D_POL: tuple[float, ...] = (161.1467, 0.0, -2.5831e-3, 6.0351e-6, -2.5573e-8)
EE3D_CENTRE: tuple[float, float] = (321.365, 236.255)
EE3D_SIZE: tuple[int, int] = (640, 480)  # (width, height)
INVPOL_COEFFS = 9


@dataclass(frozen=True)
class OcamCamera:
    """OCamCalib model. Polynomials are ascending (coefficient of power i at index i)."""

    pol: tuple[float, ...]
    invpol: tuple[float, ...]
    xc: float
    yc: float
    c: float
    d: float
    e: float
    width: int
    height: int

    # ---- geometry -------------------------------------------------------------------
    @property
    def theta_min(self) -> float:
        """Lowest ray elevation the fitted `invpol` covers (the image corners); rays
        below it are outside the field of view."""
        rho = _corner_radius(self)
        return float(np.arctan2(_polyval(self.pol, rho), rho))

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points [..., 3] -> pixels [..., 2] (u, v).

        Rays outside the field of view (see `in_fov`) are clamped to its border, so the
        result is finite but meaningless there; mask with `in_fov` / `in_image`.
        """
        pts = _as_points(points_cam)
        x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
        n = np.hypot(x, y)
        theta = np.clip(np.arctan2(z, n), self.theta_min, np.pi / 2)
        rho = self._refine_rho(_polyval(self.invpol, theta), theta)
        safe_n = np.where(n > 0, n, 1.0)  # on the axis the direction is irrelevant: rho = 0
        px, py = x / safe_n * rho, y / safe_n * rho
        u = self.xc + px * self.c + py * self.d
        v = self.yc + px * self.e + py
        return np.stack([u, v], axis=-1)

    def _refine_rho(self, rho: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """One Newton step on pol(rho) cos(theta) - rho sin(theta) = 0 from the invpol
        guess. A 9-term invpol alone is good to ~0.04 px over this lens' 286-degree
        diagonal; the step makes `project` the inverse of `backproject` to ~1e-6 px."""
        cos_t, sin_t = np.cos(theta), np.sin(theta)
        d_pol = np.polynomial.polynomial.polyder(np.asarray(self.pol, dtype=np.float64))
        residual = _polyval(self.pol, rho) * cos_t - rho * sin_t
        slope = _polyval(d_pol, rho) * cos_t - sin_t
        return np.clip(rho - residual / slope, 0.0, None)

    def backproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels [..., 2] -> unit rays [..., 3] in the camera frame."""
        uv = np.asarray(uv, dtype=np.float64)
        if uv.shape[-1:] != (2,):
            raise InputError(f"expected pixels of shape [..., 2], got {uv.shape}")
        du, dv = uv[..., 0] - self.xc, uv[..., 1] - self.yc
        # Invert [[c, d], [e, 1]] applied to (px, py).
        det = self.c - self.d * self.e
        px = (du - self.d * dv) / det
        py = (self.c * dv - self.e * du) / det
        rho = np.hypot(px, py)
        ray = np.stack([px, py, _polyval(self.pol, rho)], axis=-1)
        return ray / np.linalg.norm(ray, axis=-1, keepdims=True)

    def in_fov(self, points_cam: np.ndarray) -> np.ndarray:
        pts = _as_points(points_cam)
        theta = np.arctan2(pts[..., 2], np.hypot(pts[..., 0], pts[..., 1]))
        return theta >= self.theta_min

    def in_image(self, points_cam: np.ndarray) -> np.ndarray:
        """True where a point is in the field of view and lands on the sensor."""
        uv = self.project(points_cam)
        inside = (
            (uv[..., 0] >= -0.5) & (uv[..., 0] < self.width - 0.5)
            & (uv[..., 1] >= -0.5) & (uv[..., 1] < self.height - 0.5)
        )
        return inside & self.in_fov(points_cam)

    def pixel_rays(self, scale: float = 1.0) -> np.ndarray:
        """Unit rays [h, w, 3] through the pixel centres of the image resampled by `scale`
        (0.5: one ray per 2 x 2 block of sensor pixels, through the block's centre)."""
        h, w = round(self.height * scale), round(self.width * scale)
        u = (np.arange(w) + 0.5) / scale - 0.5
        v = (np.arange(h) + 0.5) / scale - 0.5
        uu, vv = np.meshgrid(u, v)
        return self.backproject(np.stack([uu, vv], axis=-1))

    # ---- serialisation ----------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        return {
            "model": "ocamcalib",
            "pol": list(self.pol), "invpol": list(self.invpol),
            "xc": self.xc, "yc": self.yc, "c": self.c, "d": self.d, "e": self.e,
            "width": self.width, "height": self.height,
            "convention": "x right, y down, z along the optical axis into the scene; "
            "u column, v row, no flip",
        }

    @classmethod
    def from_json(cls, obj: dict[str, Any] | str) -> "OcamCamera":
        if isinstance(obj, str):
            obj = json.loads(obj)
        try:
            return cls(
                pol=tuple(float(a) for a in obj["pol"]),
                invpol=tuple(float(a) for a in obj["invpol"]),
                xc=float(obj["xc"]), yc=float(obj["yc"]),
                c=float(obj.get("c", 1.0)), d=float(obj.get("d", 0.0)), e=float(obj.get("e", 0.0)),
                width=int(obj["width"]), height=int(obj["height"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"camera JSON needs pol, invpol, xc, yc, width, height: {exc}") from exc


def fit_invpol(
    pol: tuple[float, ...], xc: float, yc: float, width: int, height: int,
    n_coeffs: int = INVPOL_COEFFS,
) -> tuple[float, ...]:
    """Least-squares fit of rho(theta) over the radii the image rectangle covers."""
    r_max = _corner_radius_of(xc, yc, width, height)
    rho = np.linspace(0.0, r_max, 4000)
    theta = np.arctan2(_polyval(pol, rho), rho)
    vander = np.vander(theta, n_coeffs, increasing=True)
    coeffs, *_ = np.linalg.lstsq(vander, rho, rcond=None)
    return tuple(float(a) for a in coeffs)


def ee3d_default() -> OcamCamera:
    """The EE3D head-mounted fisheye with its public calibration."""
    (xc, yc), (w, h) = EE3D_CENTRE, EE3D_SIZE
    return OcamCamera(
        pol=EE3D_POL, invpol=fit_invpol(EE3D_POL, xc, yc, w, h),
        xc=xc, yc=yc, c=1.0, d=0.0, e=0.0, width=w, height=h,
    )


def sensor_to_frame_scale(sensor_hw: tuple[int, int] = (480, 640),
                          frame_hw: tuple[int, int] = (192, 256)) -> float:
    """Scale from sensor pixels to network-frame pixels (0.4 for EE3D). The benchmarks
    resize, not crop, so both axes must agree."""
    sy, sx = frame_hw[0] / sensor_hw[0], frame_hw[1] / sensor_hw[1]
    if not np.isclose(sy, sx):
        raise InputError(f"frame {frame_hw} is not a uniform resize of sensor {sensor_hw}")
    return float(sx)


def _polyval(coeffs: tuple[float, ...], x: np.ndarray | float) -> np.ndarray:
    return np.polynomial.polynomial.polyval(x, np.asarray(coeffs, dtype=np.float64))


def _corner_radius_of(xc: float, yc: float, width: int, height: int) -> float:
    dx = max(xc + 0.5, width - 0.5 - xc)
    dy = max(yc + 0.5, height - 0.5 - yc)
    return float(np.hypot(dx, dy))


def _corner_radius(cam: OcamCamera) -> float:
    return _corner_radius_of(cam.xc, cam.yc, cam.width, cam.height)


def _as_points(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-1:] != (3,):
        raise InputError(f"expected points of shape [..., 3], got {pts.shape}")
    return pts
