"""The OCamCalib fisheye model: round trip, optical axis, serialisation, frame scale."""
from __future__ import annotations

import numpy as np
import pytest

from e3dpsm.camera import EE3D_POL, OcamCamera, ee3d_default, fit_invpol, sensor_to_frame_scale
from e3dpsm.errors import InputError


@pytest.fixture(scope="module")
def cam() -> OcamCamera:
    return ee3d_default()


def test_project_inverts_backproject_over_the_whole_image(cam):
    rng = np.random.default_rng(0)
    u, v = np.meshgrid(np.arange(0, cam.width, 4.0), np.arange(0, cam.height, 4.0))
    uv = np.stack([u, v], -1) + rng.uniform(0, 4, size=u.shape + (2,))
    uv = np.minimum(uv, [cam.width - 1, cam.height - 1])
    rays = cam.backproject(uv)
    depth = rng.uniform(0.1, 5.0, size=u.shape + (1,))  # projection must ignore distance
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=1e-12)
    err = np.linalg.norm(cam.project(rays * depth) - uv, axis=-1)
    assert err.max() < 0.01


def test_optical_axis_lands_on_the_centre(cam):
    np.testing.assert_allclose(cam.project(np.array([0.0, 0.0, 2.5])), [cam.xc, cam.yc], atol=1e-9)
    np.testing.assert_allclose(cam.backproject(np.array([cam.xc, cam.yc])), [0.0, 0.0, 1.0], atol=1e-12)


def test_axes_follow_the_documented_convention(cam):
    right, down = cam.project(np.array([0.3, 0.0, 1.0])), cam.project(np.array([0.0, 0.3, 1.0]))
    assert right[0] > cam.xc + 10 and abs(right[1] - cam.yc) < 1e-9  # +x -> larger u
    assert down[1] > cam.yc + 10 and abs(down[0] - cam.xc) < 1e-9   # +y -> larger v


def test_radius_grows_with_angle_and_fov_exceeds_180_degrees(cam):
    angles = np.radians(np.arange(0, 140, 5.0))
    pts = np.stack([np.sin(angles), np.zeros_like(angles), np.cos(angles)], -1)
    radius = cam.project(pts)[:, 0] - cam.xc
    assert np.all(np.diff(radius) > 0)
    assert cam.in_image(np.array([1.0, 0.0, -0.1]))  # just behind the lens plane, still seen
    assert not cam.in_image(np.array([0.0, 0.0, -1.0]))  # straight behind: out of view


def test_fitted_invpol_alone_is_within_a_tenth_of_a_pixel(cam):
    rho = np.linspace(0, 400, 500)
    theta = np.arctan2(np.polynomial.polynomial.polyval(rho, EE3D_POL), rho)
    approx = np.polynomial.polynomial.polyval(theta, cam.invpol)
    assert len(cam.invpol) == 9
    assert np.abs(approx - rho).max() < 0.1


def test_json_round_trip_and_bad_json(cam):
    again = OcamCamera.from_json(cam.to_json())
    assert again == cam
    with pytest.raises(InputError, match="invpol"):
        OcamCamera.from_json({"pol": [1.0], "xc": 1, "yc": 1, "width": 4, "height": 4})


def test_invpol_fit_depends_on_the_image_size():
    small = fit_invpol(EE3D_POL, 160.0, 120.0, 320, 240)
    assert not np.allclose(small, ee3d_default().invpol)


def test_sensor_to_frame_scale():
    assert sensor_to_frame_scale() == pytest.approx(0.4)
    assert sensor_to_frame_scale((480, 640), (240, 320)) == pytest.approx(0.5)
    with pytest.raises(InputError, match="uniform"):
        sensor_to_frame_scale((480, 640), (192, 320))


def test_bad_shapes_are_input_errors(cam):
    with pytest.raises(InputError):
        cam.project(np.zeros((4, 2)))
    with pytest.raises(InputError):
        cam.backproject(np.zeros((4, 3)))
