"""S5 state-space layer (Smith et al., ICLR 2023) in its event-camera form (Zubic et al.,
CVPR 2024), computed in real arithmetic.

ONNX has no complex type, so every complex quantity is carried as a (real, imaginary) pair
of float tensors. The layer runs independently at every spatial location (channels-last
input [..., H]); its state is x in C^P per location:

    x_t = Lambda_bar x_(t-1) + B_bar u_t,    y_t = Re(C x_t) + D u_t

Discretisation uses the step Delta = step_scale * exp(log_step), where step_scale is the
window length over the training window: a longer window is a larger step, so one trained
model serves 20, 25 and 50 Hz.

Bidirectional: a second readout C_b of a time-reversed scan (Lambda, B and the step are
shared, as in the event-camera S5, whose C has 2P columns). In causal mode the backward
branch sees the current frame alone from a zero state, i.e. x_b,t = B_bar u_t; the same
definition serves `sequence(causal=True)` and `step`. In non-causal mode it is the full
backward scan x_b,t = Lambda_bar x_b,t+1 + B_bar u_t from a zero state after the last
frame; `backward_first_frame="own_input"` reproduces the released scan, whose first frame
is gated by the carried backward state (zero at a stream's start), so that x_b,0 = B_bar u_0.

The released code's carried *forward* state never reaches the output
(docs/model.md#citations, Carried S5 state); here the carried state is exact: chunked and
step-by-step runs reproduce whole runs.
"""
from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch
from torch import nn

from e3dpsm.layers.products import Projection

Discretization = Literal["bilinear", "zoh"]
ComplexPair = tuple[torch.Tensor, torch.Tensor]

_MIN_NEG_REAL = 1e-4  # |Re lambda| floor: keeps every mode strictly stable on unbounded streams
BACKWARD_FIRST_FRAME: tuple[str, ...] = ("scan", "own_input")
# JAX's truncated normal on [-2, 2] is rescaled by this so its variance is the requested one.
_TRUNC_NORMAL_STD = 0.87962566103423978


def hippo_legs_normal_eigs(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-decomposition of the normal part of the HiPPO-LegS matrix (Gu et al. 2022).

    Returns (lambda [P] complex, V [P, P] complex). Real parts are all -1/2.
    """
    n = np.arange(order)
    p = np.sqrt(n + 0.5)
    a = np.sqrt(2 * n[:, None] + 1) * np.sqrt(2 * n[None, :] + 1)
    legs = -np.where(n[:, None] > n[None, :], a, np.where(n[:, None] == n[None, :], n[:, None] + 1, 0.0))
    normal = legs + p[:, None] * p[None, :]  # skew-symmetric plus -1/2 I
    imag, vecs = np.linalg.eigh(normal * -1j)
    lam = np.full(order, np.mean(np.diag(normal))) + 1j * imag
    return lam, vecs


def lecun_truncated_normal(shape: tuple[int, ...], fan_in: int, gen: torch.Generator | None) -> torch.Tensor:
    """JAX's `lecun_normal` (variance 1 / fan_in, truncated at 2 std), as the released S5
    initialises B (fan-in P) and C (fan-in H * P per readout half)."""
    out = torch.empty(shape)
    nn.init.trunc_normal_(out, 0.0, 1.0, -2.0, 2.0, generator=gen)
    return out * (math.sqrt(1.0 / fan_in) / _TRUNC_NORMAL_STD)


def _expand(coeff: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """[B, P] -> [B, 1, ..., 1, P] broadcastable against `like` [B, ..., P]."""
    return coeff.view(coeff.shape[0], *([1] * (like.dim() - 2)), coeff.shape[1])


class S5(nn.Module):
    def __init__(
        self,
        dim: int,
        state_dim: int,
        *,
        bidirectional: bool = True,
        discretization: Discretization = "bilinear",
        bandlimit: float | None = 0.5,
        backward_first_frame: str = "scan",
        step_min: float = 1e-3,
        step_max: float = 1e-1,
        seed: int | None = None,
    ) -> None:
        super().__init__()
        if discretization not in ("bilinear", "zoh"):
            raise ValueError(f"unknown S5 discretisation {discretization!r}; use 'bilinear' or 'zoh'")
        if backward_first_frame not in BACKWARD_FIRST_FRAME:
            raise ValueError(f"unknown backward_first_frame {backward_first_frame!r}; use one of {BACKWARD_FIRST_FRAME}")
        self.dim, self.state_dim = dim, state_dim
        self.bidirectional, self.discretization = bidirectional, discretization
        self.backward_first_frame = backward_first_frame
        gen = torch.Generator().manual_seed(seed) if seed is not None else None

        # Initialisation as released (docs/model.md#citations, S5 layer): HiPPO-LegS
        # normal-part eigenvalues; B = V^-1 B0 with B0 LeCun-normal of fan-in P; each readout
        # C = C0 V with the real and imaginary parts of C0 LeCun-normal of fan-in H * P;
        # D ~ U[0, 1).
        lam, vecs = hippo_legs_normal_eigs(state_dim)
        v_inv = torch.from_numpy(vecs.conj().T).to(torch.complex64)
        self.log_neg_lambda_re = nn.Parameter(torch.from_numpy(np.log(-lam.real)).float())
        self.lambda_im = nn.Parameter(torch.from_numpy(lam.imag).float())

        b_tilde = v_inv @ lecun_truncated_normal((state_dim, dim), state_dim, gen).to(torch.complex64)
        self.b_re, self.b_im = nn.Parameter(b_tilde.real.clone()), nn.Parameter(b_tilde.imag.clone())

        log_step = torch.rand(state_dim, generator=gen) * (math.log(step_max) - math.log(step_min)) + math.log(step_min)
        # Band-limiting (Zubic et al. 2024): the readout columns of modes that would alias at
        # the training step are zeroed once, here, as released; training may grow them back.
        keep = torch.ones(state_dim)
        if bandlimit is not None:
            keep = (log_step.exp() * self.lambda_im.detach().abs() / (2 * math.pi) < bandlimit / 2).float()

        def readout() -> tuple[nn.Parameter, nn.Parameter]:
            fan_in = dim * state_dim
            c = torch.complex(lecun_truncated_normal((dim, state_dim), fan_in, gen),
                              lecun_truncated_normal((dim, state_dim), fan_in, gen))
            c_tilde = (c @ torch.from_numpy(vecs).to(torch.complex64)) * keep
            return nn.Parameter(c_tilde.real.clone()), nn.Parameter(c_tilde.imag.clone())

        self.c_re, self.c_im = readout()
        if bidirectional:
            self.cb_re, self.cb_im = readout()
        self.d = nn.Parameter(torch.rand(dim, generator=gen))
        self.log_step = nn.Parameter(log_step)
        self.drive_re, self.drive_im = Projection(), Projection()
        self.read_re, self.read_im = Projection(), Projection()
        if bidirectional:
            self.read_back_re, self.read_back_im = Projection(), Projection()

    # -- discretisation ------------------------------------------------------------------
    def lambda_pair(self) -> ComplexPair:
        re = -self.log_neg_lambda_re.exp().clamp_min(_MIN_NEG_REAL)
        return re, self.lambda_im

    def discretize(self, step_scale: torch.Tensor) -> tuple[ComplexPair, ComplexPair]:
        """step_scale [B] -> (Lambda_bar, gamma) as pairs of [B, P]; B_bar = gamma * B."""
        lam_re, lam_im = self.lambda_pair()
        step = step_scale.reshape(-1, 1) * self.log_step.exp().unsqueeze(0)  # [B, P]
        if self.discretization == "bilinear":
            # Lambda_bar = (1 + D lam/2)/(1 - D lam/2), gamma = D/(1 - D lam/2), expanded in
            # real and imaginary parts with alpha + i beta = D lam / 2.
            alpha, beta = step * lam_re / 2, step * lam_im / 2
            denom = (1 - alpha) ** 2 + beta**2
            bar = ((1 - alpha**2 - beta**2) / denom, 2 * beta / denom)
            gamma = (step * (1 - alpha) / denom, step * beta / denom)
        else:  # zero-order hold: Lambda_bar = exp(D lam), gamma = (Lambda_bar - 1)/lam
            mag = torch.exp(step * lam_re)
            bar = (mag * torch.cos(step * lam_im), mag * torch.sin(step * lam_im))
            norm = lam_re**2 + lam_im**2
            num_re, num_im = bar[0] - 1, bar[1]
            gamma = ((num_re * lam_re + num_im * lam_im) / norm, (num_im * lam_re - num_re * lam_im) / norm)
        return bar, gamma

    # -- pieces shared by step and sequence ----------------------------------------------
    def drive(self, u: torch.Tensor, gamma: ComplexPair) -> ComplexPair:
        """B_bar u for u [B, ..., H] -> pair of [B, ..., P]."""
        bu_re, bu_im = self.drive_re(u, self.b_re), self.drive_im(u, self.b_im)
        g_re, g_im = _expand(gamma[0], bu_re), _expand(gamma[1], bu_re)
        return g_re * bu_re - g_im * bu_im, g_re * bu_im + g_im * bu_re

    @staticmethod
    def transition(x: ComplexPair, bar: ComplexPair, v: ComplexPair) -> ComplexPair:
        l_re, l_im = _expand(bar[0], x[0]), _expand(bar[1], x[0])
        return l_re * x[0] - l_im * x[1] + v[0], l_re * x[1] + l_im * x[0] + v[1]

    def readout(self, x: ComplexPair, backward: bool = False) -> torch.Tensor:
        if backward:
            return self.read_back_re(x[0], self.cb_re) - self.read_back_im(x[1], self.cb_im)
        return self.read_re(x[0], self.c_re) - self.read_im(x[1], self.c_im)

    # -- public API ----------------------------------------------------------------------
    def step(self, u: torch.Tensor, state: ComplexPair, step_scale: torch.Tensor) -> tuple[torch.Tensor, ComplexPair]:
        """One time step: u [B, ..., H], state pair of [B, ..., P]."""
        bar, gamma = self.discretize(step_scale)
        v = self.drive(u, gamma)
        x = self.transition(state, bar, v)
        y = self.readout(x) + u * self.d
        if self.bidirectional:
            y = y + self.readout(v, backward=True)
        return y, x

    def sequence(
        self, u: torch.Tensor, state: ComplexPair | None, step_scale: torch.Tensor, causal: bool
    ) -> tuple[torch.Tensor, ComplexPair]:
        """A whole sequence u [B, T, ..., H]; returns (y [B, T, ..., H], final forward state).

        The input drive is computed for all T at once; the recurrence itself is a loop over
        T of elementwise ops, cheaper on CPU than an O(T^2) convolution kernel for T ~ 40.
        """
        bar, gamma = self.discretize(step_scale)
        v_re, v_im = self.drive(u, gamma)
        if state is None:
            zeros = v_re.new_zeros(v_re[:, 0].shape)
            state = (zeros, zeros)
        x, outs = state, []
        for t in range(u.shape[1]):
            x = self.transition(x, bar, (v_re[:, t], v_im[:, t]))
            outs.append(x)
        xs = (torch.stack([o[0] for o in outs], 1), torch.stack([o[1] for o in outs], 1))
        y = self.readout(xs) + u * self.d
        if self.bidirectional:
            if causal:
                y = y + self.readout((v_re, v_im), backward=True)
            else:
                zeros = v_re.new_zeros(v_re[:, 0].shape)
                xb, back = (zeros, zeros), []
                for t in reversed(range(u.shape[1])):
                    xb = self.transition(xb, bar, (v_re[:, t], v_im[:, t]))
                    back.append(xb)
                back.reverse()
                if self.backward_first_frame == "own_input":
                    back[0] = (v_re[:, 0], v_im[:, 0])
                xbs = (torch.stack([o[0] for o in back], 1), torch.stack([o[1] for o in back], 1))
                y = y + self.readout(xbs, backward=True)
        return y, x


class S5Block(nn.Module):
    """Residual S5 block on a feature map [B, C, h, w] (per-location over time), as
    released (docs/model.md#citations, S5 placement and block):
    n = LN1 x; h = n + GELU(S5(n)); m = LN2 h; out = m + GEGLU(m)
    with a bias-free feed-forward of width C.

    Both residuals carry the *normed* tensor, so the block re-normalises the encoder's
    residual stream. This matters: the pre-activation residual blocks leave the stream
    unnormalised and it grows about 10x per stage. With a plain pre-norm residual
    (x + GELU(S5(LN x))) instead, the `small` model fed the decoder memory of magnitude
    ~3,000. After 2,600 training steps its decoder output had collapsed to a constant,
    i.e. the mean pose, with a per-frame std of 4e-4.
    """

    def __init__(self, dim: int, state_dim: int, ff_hidden: int | None = None, **s5_kwargs) -> None:
        super().__init__()
        from e3dpsm.layers.feedforward import GEGLU

        self.norm1 = nn.LayerNorm(dim)
        self.s5 = S5(dim, state_dim, **s5_kwargs)
        self.act = nn.GELU()
        self.norm2 = nn.LayerNorm(dim)
        self.ff = GEGLU(dim, dim if ff_hidden is None else ff_hidden, bias=False)

    def _ff(self, h: torch.Tensor) -> torch.Tensor:
        normed = self.norm2(h)
        return normed + self.ff(normed)

    def step(self, x: torch.Tensor, state: ComplexPair, step_scale: torch.Tensor) -> tuple[torch.Tensor, ComplexPair]:
        """x: [B, C, h, w]; state: pair of [B, h, w, P]."""
        normed = self.norm1(x.permute(0, 2, 3, 1))
        y, state = self.s5.step(normed, state, step_scale)
        return self._ff(normed + self.act(y)).permute(0, 3, 1, 2), state

    def sequence(
        self, x: torch.Tensor, state: ComplexPair | None, step_scale: torch.Tensor, causal: bool
    ) -> tuple[torch.Tensor, ComplexPair]:
        """x: [B, T, C, h, w]."""
        normed = self.norm1(x.permute(0, 1, 3, 4, 2))
        y, state = self.s5.sequence(normed, state, step_scale, causal)
        return self._ff(normed + self.act(y)).permute(0, 1, 4, 2, 3), state
