"""The model's maths against independent references: numpy complex arithmetic for the S5
discretisation, explicit loops for the scans, the textbook matrix-form Kalman filter, and
the first-step rule. Each test names the one-line bug it exists to catch."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import e3dpsm
from e3dpsm.layers import S5, PoseFusion
from tests.conftest import sparse_lnes


def _complex(re: torch.Tensor, im: torch.Tensor) -> np.ndarray:
    return re.detach().double().numpy() + 1j * im.detach().double().numpy()


def _s5_numpy(s5: S5, window_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(Lambda_bar, gamma) of the bilinear transform, in complex128."""
    lam = -np.maximum(np.exp(s5.log_neg_lambda_re.detach().double().numpy()), 1e-4) \
        + 1j * s5.lambda_im.detach().double().numpy()
    step = window_scale * np.exp(s5.log_step.detach().double().numpy())
    return (1 + step * lam / 2) / (1 - step * lam / 2), step / (1 - step * lam / 2)


@pytest.mark.parametrize("window_ms", [20.0, 25.0, 50.0])
def test_step_s5_state_matches_numpy_complex_discretisation(window_ms: float) -> None:
    """Catches: the window scale inverted (train / window), the sign of Im(Lambda_bar) flipped.

    The model's S5 state update x' = Lambda_bar x + gamma B u against numpy complex128 with
    Delta = (window / 20 ms) * exp(log_step), from a non-zero carried state."""
    model = e3dpsm.create_model("tiny").eval()
    captured = {}
    model.attention[3].register_forward_hook(lambda mod, inp, out: captured.__setitem__("x", out))
    state = model.init_state(1)
    gen = torch.Generator().manual_seed(0)
    state["s5_stage4_re"] = torch.randn(state["s5_stage4_re"].shape, generator=gen)
    state["s5_stage4_im"] = torch.randn(state["s5_stage4_im"].shape, generator=gen)
    with torch.no_grad():
        _, new = model.step(sparse_lnes((1, 2, 192, 256), seed=4), state, window_ms)
        block = model.ssm["3"]
        u = block.norm1(captured["x"].permute(0, 2, 3, 1)).double().numpy()  # [1, h, w, H]
    s5 = block.s5
    lam_bar, gamma = _s5_numpy(s5, window_ms / model.config.train_window_ms)
    drive = u @ _complex(s5.b_re, s5.b_im).T  # B u, [1, h, w, P]
    expected = lam_bar * _complex(state["s5_stage4_re"], state["s5_stage4_im"]) + gamma * drive
    got = _complex(new["s5_stage4_re"], new["s5_stage4_im"])
    assert np.abs(got - expected).max() <= 1e-5 * np.abs(expected).max()
    assert np.abs(lam_bar.imag).max() > 1e-3  # the imaginary part is exercised


def _scan_reference(s5: S5, u: np.ndarray, scale: float, causal: bool, first: str) -> np.ndarray:
    """y_t = Re(C x_t) + Re(C_b xb_t) + D u_t with both scans written as explicit loops."""
    lam_bar, gamma = _s5_numpy(s5, scale)
    drive = gamma * (u @ _complex(s5.b_re, s5.b_im).T)  # [B, T, ..., P]
    steps = u.shape[1]
    fwd, back = np.zeros_like(drive), np.zeros_like(drive)
    x = np.zeros_like(drive[:, 0])
    for t in range(steps):
        x = lam_bar * x + drive[:, t]
        fwd[:, t] = x
    if causal:
        back = drive
    else:
        x = np.zeros_like(drive[:, 0])
        for t in range(steps - 1, -1, -1):
            x = lam_bar * x + drive[:, t]
            back[:, t] = x
        if first == "own_input":
            back[:, 0] = drive[:, 0]
    c, cb = _complex(s5.c_re, s5.c_im), _complex(s5.cb_re, s5.cb_im)
    return (fwd @ c.T).real + (back @ cb.T).real + u * s5.d.detach().double().numpy()


@pytest.mark.parametrize("causal, first", [(True, "scan"), (False, "scan"), (False, "own_input")])
def test_s5_sequence_matches_explicit_scans(causal: bool, first: str) -> None:
    """Catches: the non-causal backward scan not reversed; the released t = 0 rule lost."""
    s5 = S5(6, 5, bidirectional=True, backward_first_frame=first, seed=3)
    with torch.no_grad():  # trained-like: modes that ring, and readouts that are not zeroed
        s5.log_step.fill_(np.log(0.3))
        for p in (s5.c_re, s5.c_im, s5.cb_re, s5.cb_im):
            p.normal_(0, 0.5, generator=torch.Generator().manual_seed(p.numel()))
    u = torch.randn(2, 7, 3, 6, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        y, _ = s5.sequence(u, None, torch.tensor([1.25]), causal=causal)
    expected = _scan_reference(s5, u.double().numpy(), 1.25, causal, first)
    assert np.abs(y.double().numpy() - expected).max() <= 1e-5 * np.abs(expected).max()


def test_kalman_step_matches_matrix_form_with_inverse() -> None:
    """Catches: the gain R / (P + R) instead of P / (P + R); a wrong covariance update.

    Reference: the released filter's matrix form (S = H P H' + R, K = P H' S^-1, Joseph
    update), 48 x 48 matrices, numpy inverse."""
    fusion = PoseFusion(16, "learned")
    rng = np.random.default_rng(1)
    with torch.no_grad():
        fusion.log_q.copy_(torch.from_numpy(rng.normal(np.log(20.0), 0.5, (16, 3))))
        fusion.log_r.copy_(torch.from_numpy(rng.normal(np.log(50.0), 0.5, (16, 3))))
    prev, direct, delta = (torch.from_numpy(rng.normal(0, s, (1, 16, 3))).float() for s in (400.0, 400.0, 30.0))
    prev_cov = torch.from_numpy(rng.uniform(5.0, 80.0, (1, 16, 3))).float()
    with torch.no_grad():
        fused, cov = fusion(direct, delta, prev, prev_cov, torch.ones(1, 1))

    eye = np.eye(48)
    q, r = np.diag(fusion.log_q.exp().detach().double().numpy().ravel()), np.diag(fusion.log_r.exp().detach().double().numpy().ravel())
    x = prev.double().numpy().reshape(48, 1) + delta.double().numpy().reshape(48, 1)  # A = B = I
    p = np.diag(prev_cov.double().numpy().ravel()) + q
    gain = p @ np.linalg.inv(p + r)  # H = I
    x = x + gain @ (direct.double().numpy().reshape(48, 1) - x)
    p = (eye - gain) @ p @ (eye - gain).T + gain @ r @ gain.T
    assert np.abs(fused.double().numpy().reshape(48) - x[:, 0]).max() <= 1e-3  # mm
    assert np.abs(cov.double().numpy().reshape(48) - np.diag(p)).max() <= 1e-4 * np.diag(p).max()
    assert 0.1 < np.diag(gain).min() and np.diag(gain).max() < 0.9  # a gain that tells P from R


def test_first_step_of_a_stream_is_the_direct_pose(tiny_model) -> None:
    """Catches: the first-step handling removed (the filter would fuse with a zero pose)."""
    lnes = sparse_lnes((2, 2, 2, 192, 256), seed=9)
    with torch.no_grad():
        first, state = tiny_model.step(lnes[:, 0], tiny_model.init_state(2))
        second, _ = tiny_model.step(lnes[:, 1], state)
    assert torch.equal(first["pose"], first["pose_direct"])
    assert torch.equal(state["fusion_pose"], first["pose_direct"])
    assert torch.all(state["fusion_cov"] == tiny_model.fusion.p0) and torch.all(state["fusion_initialised"] == 1)
    assert (second["pose"] - second["pose_direct"]).abs().max() > 1e-3  # later steps do fuse


def test_band_limit_zeroes_aliasing_readouts_once_at_construction() -> None:
    """As released: modes with step * |Im lambda| / (2 pi) >= bandlimit / 2 get zero readout
    columns at construction (numpy reference), and the readout uses C as it stands, so a
    column trained back to non-zero counts (a mask applied at every readout would not)."""
    s5 = S5(4, 32, bidirectional=True, bandlimit=0.5, seed=0)
    freq = np.exp(s5.log_step.detach().double().numpy()) * np.abs(s5.lambda_im.detach().double().numpy()) / (2 * np.pi)
    aliasing = freq >= 0.25
    assert 0 < aliasing.sum() < aliasing.size  # both kinds of mode are present
    for c in (s5.c_re, s5.c_im, s5.cb_re, s5.cb_im):
        assert torch.all(c[:, torch.from_numpy(aliasing)] == 0) and torch.any(c[:, torch.from_numpy(~aliasing)] != 0)
    mode = int(np.flatnonzero(aliasing)[0])
    x = (torch.zeros(1, 32), torch.zeros(1, 32))
    x[0][0, mode] = 1.0
    with torch.no_grad():
        s5.c_re[:, mode] = 1.0  # "trained back"
    assert torch.equal(s5.readout(x), torch.ones(1, 4))


@pytest.mark.parametrize("height, width, samples", [(2, 4, False), (3, 3, True)])
def test_attention_skips_sampling_on_maps_of_at_most_points_tokens(height: int, width: int, samples: bool) -> None:
    """As released: with h*w <= points tokens the block uses the value projection alone."""
    from e3dpsm.layers import DeformableTransformerBlock

    block = DeformableTransformerBlock(8, 2, 4, 8, height, width, layout="1d").eval()
    x = torch.randn(1, 8, height, width, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        before = block(x)
        for p in block.attn.parameters():
            p.add_(0.5)
        assert torch.equal(block(x), before) is not samples
