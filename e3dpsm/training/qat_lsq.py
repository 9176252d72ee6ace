"""Learned activation ranges for quantisation-aware fine-tuning (LSQ / LSQ+).

One `LearnedQuantizer` per tensor the INT8 graph quantises (qat_sites.py finds them): an
asymmetric U8 per-tensor quantiser with a learned step size `scale` (Esser et al., ICLR 2020,
"Learned Step Size Quantization") and a learned offset (Bhalgat et al., CVPRW 2020, "LSQ+"),
trained by straight-through gradients through the recurrent rollout.

The forward pass is ONNX Runtime's QuantizeLinear -> DequantizeLinear on the same numbers,
in the same order (MLAS divides by the scale, rounds half to even, adds the zero point,
saturates; DequantizeLinear multiplies (q - zero_point) by the scale), so the graph built
from the learned (scale, zero_point) computes what training simulated. ONNX needs an integer
zero point, so the offset is learned as a real number and rounded (straight through) in the
forward pass; `qparams()` gives the very float32 scale and integer zero point used.

Gradients (all by autograd on the expression in `fake_quantize_learned`):
- x: 1 inside the range, 0 where it saturates;
- scale: round(x/s) - x/s inside, (qmin - z) or (qmax - z) where it saturates (LSQ);
- zero point: 0 inside, -s where it saturates (LSQ+ offset).
The scale is learned as its logarithm: Adam moves a parameter by about its learning rate
per step whatever the gradient's size, so in log space that is a relative change, the same
for a range of 0.01 as for one of 100 (LSQ's gradient scale 1/sqrt(numel * qmax) addresses
the same problem for SGD, and cancels out under Adam).
"""
from __future__ import annotations

import math

import torch
from torch import nn

QMIN, QMAX = 0, 255   # U8 activations (quantize/static.py StaticConfig.activation_type)
MIN_SCALE = 1e-8


def round_ste(x: torch.Tensor) -> torch.Tensor:
    """Round half to even in the forward pass, identity gradient."""
    return x + (torch.round(x) - x).detach()


def fake_quantize_learned(x: torch.Tensor, scale: torch.Tensor, zero_point: torch.Tensor) -> torch.Tensor:
    """QuantizeLinear then DequantizeLinear (U8, per tensor) with straight-through gradients.
    `zero_point` may be real: it is rounded (half to even) and clipped to [QMIN, QMAX]."""
    s = scale.clamp_min(MIN_SCALE).to(x.dtype)
    z = round_ste(zero_point).clamp(QMIN, QMAX).to(x.dtype)
    q = torch.clamp(round_ste(x / s) + z, QMIN, QMAX)
    return (q - z) * s


class RangeObserver:
    """A tensor's calibration values seen by a quantiser that does not quantise yet: on the
    first pass its min and max, on the second (`start_histogram`) a histogram of them on that
    range, as `quantize --calibration mse` collects them on the graph (quantize/ranges.py)."""

    def __init__(self) -> None:
        self.low, self.high = math.inf, -math.inf
        self.counts: torch.Tensor | None = None

    def start_histogram(self, bins: int) -> None:
        if self.high >= self.low:
            self.low, self.high = min(self.low, 0.0), max(self.high, 0.0)
            self.counts = torch.zeros(bins, dtype=torch.float64)

    def observe(self, x: torch.Tensor) -> None:
        x = x.detach().float()
        if self.counts is None:
            low, high = torch.aminmax(x)
            self.low, self.high = min(self.low, float(low)), max(self.high, float(high))
        elif self.high > self.low:
            # Values outside the first pass's range (none, on the same windows) go to the end bins.
            self.counts += torch.histc(x.clamp(self.low, self.high), len(self.counts), self.low, self.high).double()


class LearnedQuantizer(nn.Module):
    """A learned U8 range for one quantised tensor; initialised from calibration windows
    (`FakeQuantHandle.calibrate`) or else from the first batch it sees (its min-max, widened
    to hold 0, as ONNX Runtime's calibrator makes it)."""

    def __init__(self) -> None:
        super().__init__()
        self.log_scale = nn.Parameter(torch.tensor(0.0))
        self.zero_point = nn.Parameter(torch.tensor(0.0))
        self.register_buffer("initialised", torch.tensor(False))
        # Set while calibrating: the forward pass records its input and returns it unchanged.
        self.observer: RangeObserver | None = None

    def init_from_range(self, low: float, high: float) -> None:
        low, high = min(float(low), 0.0), max(float(high), 0.0)
        scale = max((high - low) / (QMAX - QMIN), MIN_SCALE)
        with torch.no_grad():
            self.log_scale.fill_(math.log(scale))
            self.zero_point.fill_(float(min(max(round(QMIN - low / scale), QMIN), QMAX)))
            self.initialised.fill_(True)

    def set_qparams(self, scale: float, zero_point: int) -> None:
        with torch.no_grad():
            self.log_scale.fill_(math.log(float(scale)))
            self.zero_point.fill_(float(zero_point))
            self.initialised.fill_(True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.observer is not None:
            self.observer.observe(x)
            return x
        if not bool(self.initialised):
            low, high = torch.aminmax(x.detach())
            if not float(high) - float(low) > 0.0:
                # A constant first batch (the Kalman fusion's pose input is all zeros before
                # its first frame) has no range to start from: a scale at MIN_SCALE would zero
                # the tensor and Adam moves the log-scale by about its learning rate per step,
                # so it never recovers. Pass it through; start from the first batch that varies.
                return x
            self.init_from_range(float(low), float(high))
        return fake_quantize_learned(x, self.scale, self.zero_point)

    @property
    def scale(self) -> torch.Tensor:
        return torch.exp(self.log_scale)

    def qparams(self) -> tuple[float, int]:
        """(float32 scale, integer zero point) exactly as the forward pass applies them."""
        scale = float(self.scale.detach().clamp_min(MIN_SCALE).to(torch.float32))
        zero = int(torch.round(self.zero_point.detach()).clamp(QMIN, QMAX))
        return scale, zero
