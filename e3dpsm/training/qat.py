"""Quantisation-aware fine-tuning: train with the rounding the INT8 graph will apply.

`e3dpsm quantize --mode int8` quantises statically (quantize/static.py, ONNX Runtime QDQ):
per-tensor asymmetric U8 on the inputs and outputs of every Conv / MatMul / Gemm, symmetric
S8 weights per output channel, the recurrent path (S5 core, Kalman fusion and the heads it
reads; quantize/graph_groups.py) in float. A network trained in float alone has sharp
activations (max/rms up to 26 in the trained `small`'s first stage), so one rounding step
of a per-tensor U8 range is several percent of a typical value and the held-out poses move
by several percent of the MPJPE (benchmarks/results/quantize_small_trained_int8.md).

Fine-tuning with that rounding in the forward pass (straight-through gradients, Jacob et
al., CVPR 2018, "Quantization and Training of Neural Networks for Efficient
Integer-Arithmetic-Only Inference") lets the weights adapt to it. The ranges here follow the
batches (an exponential moving average of each batch's min/max); the exported graph is
calibrated afresh by `quantize`, so nothing of this module reaches a checkpoint or a graph:
`attach_fake_quant` hooks the model, `FakeQuantHandle.remove` leaves it as it was.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterator

import torch
from torch import nn
from torch.nn.utils import parametrize

# Modules the INT8 graph keeps in float whatever the search decides: the Kalman fusion's
# pose embedding and the delta head feeding it (graph_groups' `fusion` recurrent group:
# `inject` stops at the first projection). The S5 recurrence has no nn.Linear of its own.
FLOAT_MODULE_PREFIXES: tuple[str, ...] = ("fusion", "pose_embed", "delta_head")
ACTIVATION_QMIN, ACTIVATION_QMAX = 0, 255      # U8 (StaticConfig.activation_type)
WEIGHT_QMAX = 127                              # S8 symmetric, per output channel


@dataclass(frozen=True)
class QATConfig:
    """How the rounding is simulated. `momentum`: weight of each new batch in the running
    activation range (the range settles within ~1/momentum steps)."""

    momentum: float = 0.01
    weights: bool = True
    activations: bool = True


def fake_quantize_weight(weight: torch.Tensor) -> torch.Tensor:
    """Symmetric S8 per output channel (axis 0), zero point 0; gradients pass straight
    through inside the range."""
    absmax = weight.detach().abs().flatten(1).amax(dim=1).clamp_min(1e-12)
    scale = (absmax / WEIGHT_QMAX).to(torch.float32)
    zero = torch.zeros_like(scale, dtype=torch.int32)
    return torch.fake_quantize_per_channel_affine(weight, scale, zero, 0, -WEIGHT_QMAX, WEIGHT_QMAX)


class RangeObserver:
    """Running [min, max] of one activation, widened to include 0 (so 0 is exact, as ONNX
    Runtime's calibrator makes it)."""

    def __init__(self, momentum: float) -> None:
        self.momentum = momentum
        self.low: float | None = None
        self.high: float | None = None

    def update(self, x: torch.Tensor) -> None:
        low, high = torch.aminmax(x.detach())
        low, high = min(float(low), 0.0), max(float(high), 0.0)
        if self.low is None:
            self.low, self.high = low, high
        else:
            self.low += self.momentum * (low - self.low)
            self.high += self.momentum * (high - self.high)

    def scale_zero_point(self) -> tuple[float, int]:
        span = max(self.high - self.low, 1e-8)
        scale = span / (ACTIVATION_QMAX - ACTIVATION_QMIN)
        zero = int(round(ACTIVATION_QMIN - self.low / scale))
        return scale, min(max(zero, ACTIVATION_QMIN), ACTIVATION_QMAX)

    def fake_quantize(self, x: torch.Tensor, observe: bool) -> torch.Tensor:
        if observe or self.low is None:
            self.update(x)
        scale, zero = self.scale_zero_point()
        return torch.fake_quantize_per_tensor_affine(x, scale, zero, ACTIVATION_QMIN, ACTIVATION_QMAX)


class _WeightFakeQuant(nn.Module):
    def forward(self, weight: torch.Tensor) -> torch.Tensor:
        return fake_quantize_weight(weight)


def quantised_modules(model: nn.Module) -> list[tuple[str, nn.Module]]:
    """(name, module) of every Conv2d / Linear that the INT8 graph quantises."""
    return [(name, module) for name, module in model.named_modules()
            if isinstance(module, (nn.Conv2d, nn.Linear))
            and not any(name == p or name.startswith(p + ".") for p in FLOAT_MODULE_PREFIXES)]


class FakeQuantHandle:
    """The hooks and weight parametrisations one `attach_fake_quant` call added."""

    def __init__(self, model: nn.Module, config: QATConfig) -> None:
        self.model, self.config = model, config
        self.modules = quantised_modules(model)
        self.observers: dict[str, tuple[RangeObserver, RangeObserver]] = {}
        self._hooks: list[torch.utils.hooks.RemovableHandle] = []
        self._weights_attached = False

    def _attach_weights(self) -> None:
        if self.config.weights and not self._weights_attached:
            for _, module in self.modules:
                parametrize.register_parametrization(module, "weight", _WeightFakeQuant())
            self._weights_attached = True

    def _detach_weights(self) -> None:
        if self._weights_attached:
            for _, module in self.modules:
                # leave_parametrized=False puts the original Parameter object back, so an
                # optimizer built on the parameters keeps tracking the same tensors.
                parametrize.remove_parametrizations(module, "weight", leave_parametrized=False)
            self._weights_attached = False

    def _attach_hooks(self) -> None:
        if not self.config.activations:
            return
        for name, module in self.modules:
            inp, out = self.observers.setdefault(
                name, (RangeObserver(self.config.momentum), RangeObserver(self.config.momentum)))

            def before(mod: nn.Module, args: tuple, inp: RangeObserver = inp) -> tuple:
                return (inp.fake_quantize(args[0], observe=mod.training), *args[1:])

            def after(mod: nn.Module, args: tuple, output: torch.Tensor, out: RangeObserver = out) -> torch.Tensor:
                return out.fake_quantize(output, observe=mod.training)

            self._hooks.append(module.register_forward_pre_hook(before))
            self._hooks.append(module.register_forward_hook(after))

    def attach(self) -> "FakeQuantHandle":
        self._attach_weights()
        self._attach_hooks()
        return self

    def remove(self) -> None:
        for hook in self._hooks:
            hook.remove()
        self._hooks.clear()
        self._detach_weights()

    @property
    def attached(self) -> bool:
        return self._weights_attached or bool(self._hooks)

    @contextlib.contextmanager
    def removed(self) -> Iterator[nn.Module]:
        """The plain model for a while (to save a checkpoint); ranges survive. Re-attaches
        only what was attached on entry, so a handle removed for good stays removed."""
        was_attached = self.attached
        self.remove()
        try:
            yield self.model
        finally:
            if was_attached:
                self.attach()


def attach_fake_quant(model: nn.Module, config: QATConfig | None = None) -> FakeQuantHandle:
    """Fake-quantise `model` in place as the default INT8 graph quantises it; returns the
    handle that removes it again."""
    return FakeQuantHandle(model, config or QATConfig()).attach()
