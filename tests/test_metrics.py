"""Metric definitions on hand-made cases whose answers are known in closed form."""
from __future__ import annotations

import numpy as np
import pytest

from e3dpsm.errors import InputError
from e3dpsm.metrics import e_smooth, mpjpe, pa_mpjpe, procrustes_align


def _random_poses(n: int = 5, j: int = 16, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(0.0, 300.0, size=(n, j, 3)) + np.array([0.0, 0.0, 1000.0])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def test_mpjpe_of_known_offset_equals_offset_length() -> None:
    gt = _random_poses()
    offset = np.array([30.0, -40.0, 0.0])  # length 50 mm
    assert mpjpe(gt + offset, gt) == pytest.approx(50.0, abs=1e-9)


def test_mpjpe_is_not_root_relative() -> None:
    gt = _random_poses()
    # A global translation is a real error: a root-relative metric would report 0.
    assert mpjpe(gt + np.array([0.0, 0.0, 100.0]), gt) == pytest.approx(100.0, abs=1e-9)


def test_pa_mpjpe_vanishes_for_similarity_transformed_prediction() -> None:
    rng = np.random.default_rng(1)
    gt = _random_poses(seed=2)
    pred = np.stack([1.7 * frame @ _random_rotation(rng).T + rng.normal(0, 500, 3) for frame in gt])
    assert mpjpe(pred, gt) > 100.0
    assert pa_mpjpe(pred, gt) == pytest.approx(0.0, abs=1e-6)


def test_pa_alignment_never_reflects() -> None:
    gt = _random_poses(seed=3)
    mirrored = gt * np.array([-1.0, 1.0, 1.0])
    aligned = procrustes_align(mirrored, gt)
    # A reflection would undo the mirror exactly; the proper-rotation fix must leave error.
    assert pa_mpjpe(mirrored, gt) > 10.0
    # A rotation with positive scale keeps the handedness (sign of a triple product).
    def handedness(poses: np.ndarray) -> np.ndarray:
        v = poses[:, 1:4] - poses[:, :1]
        return np.sign(np.einsum("ni,ni->n", np.cross(v[:, 0], v[:, 1]), v[:, 2]))
    np.testing.assert_array_equal(handedness(aligned), handedness(mirrored))


def test_pa_mpjpe_is_at_most_mpjpe() -> None:
    gt = _random_poses(seed=4)
    pred = gt + np.random.default_rng(5).normal(0, 40.0, gt.shape)
    assert pa_mpjpe(pred, gt) <= mpjpe(pred, gt) + 1e-9


def test_e_smooth_is_zero_for_matching_constant_velocity() -> None:
    t = np.arange(10, dtype=np.float64)[:, None, None]
    gt = _random_poses(1) + t * np.array([3.0, 4.0, 0.0])  # speed 5 mm/frame
    pred = gt[:1] + np.array([100.0, 0.0, 0.0]) + t * np.array([0.0, 0.0, 5.0])  # same speed, other way
    assert e_smooth(pred, gt) == pytest.approx(0.0, abs=1e-9)
    assert e_smooth(gt[:1].repeat(10, axis=0), gt) == pytest.approx(5.0, abs=1e-9)


def test_visible_mask_selects_joints() -> None:
    gt = np.zeros((4, 16, 3))
    pred = gt.copy()
    pred[:, :8, 0] = 10.0
    pred[:, 8:, 0] = 30.0
    mask = np.zeros((4, 16), dtype=np.uint8)
    mask[:, 8:] = 1
    assert mpjpe(pred, gt) == pytest.approx(20.0)
    assert mpjpe(pred, gt, mask) == pytest.approx(30.0)
    assert mpjpe(pred, gt, mask == 0) == pytest.approx(10.0)
    assert np.isnan(mpjpe(pred, gt, np.zeros((4, 16))))


def test_e_smooth_mask_uses_later_frame() -> None:
    gt = np.zeros((3, 2, 3))
    pred = gt.copy()
    pred[1, 0, 0] = 6.0  # joint 0 jumps out at t=1 and back at t=2: errors 6 and 6
    mask = np.array([[1, 1], [0, 1], [1, 1]])
    assert e_smooth(pred, gt) == pytest.approx(12.0 / 4)
    assert e_smooth(pred, gt, mask) == pytest.approx(6.0 / 3)


def test_shape_mismatch_is_an_input_error() -> None:
    with pytest.raises(InputError, match=r"\[N, J, 3\]"):
        mpjpe(np.zeros((2, 16, 3)), np.zeros((3, 16, 3)))
    with pytest.raises(InputError, match="mask"):
        mpjpe(np.zeros((2, 16, 3)), np.zeros((2, 16, 3)), np.ones((2, 15)))


# Written against survivors of `mutmut run --paths-to-mutate e3dpsm/metrics.py` (2026-12-03).


def _horn_alignment(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """An independent reference for one frame: Horn's closed form (J. Opt. Soc. Am. A 4(4),
    1987), the rotation as the unit quaternion of the largest eigenvalue of a 4 x 4 matrix,
    a proper rotation by construction, then the least-squares scale and translation."""
    p, g = pred - pred.mean(0), gt - gt.mean(0)
    (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = p.T @ g  # S_ab = sum p_a g_b
    n = np.array([[sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
                  [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
                  [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
                  [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz]])
    w, x, y, z = np.linalg.eigh(n)[1][:, -1]
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    rp = p @ rotation.T
    return (rp * g).sum() / (p * p).sum() * rp + gt.mean(0)


@pytest.mark.parametrize("mirror", [False, True])
def test_pa_alignment_is_horns(mirror: bool) -> None:
    """Procrustes alignment against Horn's quaternion solution. Mirrored, the best orthogonal
    map is a reflection: Umeyama's fix must flip the direction of the smallest singular value
    (flipping another still gives a rotation, a worse one); Horn's form never reflects."""
    rng = np.random.default_rng(6)
    gt = _random_poses(n=3, seed=6) * np.array([1.0, 0.6, 0.3])  # distinct singular values
    pred = np.stack([0.8 * f @ _random_rotation(rng).T for f in gt]) + rng.normal(0, 30.0, gt.shape)
    if mirror:
        pred = pred * np.array([-1.0, 1.0, 1.0])
    aligned = procrustes_align(pred, gt)
    for n in range(len(gt)):
        np.testing.assert_allclose(aligned[n], _horn_alignment(pred[n], gt[n]), rtol=0, atol=1e-6)


@pytest.mark.parametrize("unit", [1e-3, 1e-4])
def test_pa_mpjpe_scales_with_the_units(unit: float) -> None:
    """Poses in another unit give the PA-MPJPE in that unit: metres (1e-3), and units small
    enough that the prediction's summed squared spread is below 1 (1e-4), where a scale
    rule tied to the numbers' size would fail."""
    gt = _random_poses(seed=7)
    pred = gt + np.random.default_rng(8).normal(0, 40.0, gt.shape)
    spread = (((pred - pred.mean(axis=1, keepdims=True)) * unit) ** 2).sum(axis=(1, 2)).max()
    assert spread < 1.0 if unit == 1e-4 else spread > 1.0  # the two sides of such a rule
    assert pa_mpjpe(pred * unit, gt * unit) == pytest.approx(pa_mpjpe(pred, gt) * unit, rel=1e-9)


def test_a_collapsed_prediction_aligns_to_the_ground_truths_centre() -> None:
    """A prediction whose joints are one point has no rotation or scale: it is moved to the
    ground truth's centroid, and the error is the joints' distance to it."""
    gt = _random_poses(n=2, seed=9)
    pred = np.zeros_like(gt) + np.array([1.0, 2.0, 3.0])
    aligned = procrustes_align(pred, gt)
    np.testing.assert_allclose(aligned, np.broadcast_to(gt.mean(axis=1, keepdims=True), gt.shape), atol=1e-9)
    centroid_distance = np.linalg.norm(gt - gt.mean(axis=1, keepdims=True), axis=-1).mean()
    assert pa_mpjpe(pred, gt) == pytest.approx(centroid_distance, rel=1e-12)


def test_e_smooth_mask_has_one_row_per_frame() -> None:
    gt = _random_poses(n=6, j=4, seed=10)
    pred = gt + np.random.default_rng(11).normal(0, 5.0, gt.shape)
    mask = np.ones((6, 4))
    assert e_smooth(pred, gt, mask) == pytest.approx(e_smooth(pred, gt))
    with pytest.raises(InputError, match=r"joint mask of shape \[6, 4\], got \[5, 4\]"):
        e_smooth(pred, gt, np.ones((5, 4)))


@pytest.mark.parametrize("shape", [(2, 16, 2), (2, 16, 4), (16, 3)])
def test_poses_must_be_three_dimensional_points(shape) -> None:
    with pytest.raises(InputError, match=r"expected pred and gt of equal shape \[N, J, 3\]"):
        mpjpe(np.zeros(shape), np.zeros(shape))
