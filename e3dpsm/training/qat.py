"""Quantisation-aware fine-tuning: train with the rounding the INT8 graph will apply.

`e3dpsm quantize --mode int8` quantises statically (quantize/static.py, ONNX Runtime QDQ):
per-tensor asymmetric U8 on the inputs and outputs of every Conv / MatMul / Gemm, symmetric
S8 weights per output channel, the recurrent path (S5 core, Kalman fusion and the heads it
reads; quantize/graph_groups.py) in float. A network trained in float alone has sharp
activations (max/rms up to 26 in the trained `small`'s first stage), so one rounding step
of a per-tensor U8 range is several percent of a typical value and the held-out poses move
by several percent of the MPJPE (benchmarks/results/quantize_small_trained_int8.md).

Fine-tuning with that rounding in the forward pass (straight-through gradients, Jacob et
al., CVPR 2018) lets the weights adapt to it. The activation ranges are learned (LSQ / LSQ+,
qat_lsq.py) at exactly the tensors the INT8 graph quantises: `attach_fake_quant` exports
the model once, finds the tensors that get a QuantizeLinear (recurrent groups in float) and
the PyTorch sites holding the same numbers (qat_sites.py, e3dpsm/training/qat_ranges.py), and hooks
one learned quantiser per such group. The checkpoint carries the learned ranges
(`qat_ranges`, `FakeQuantHandle.ranges_payload`) beside the plain weights, and
`quantize --ranges-from-checkpoint` writes them into the graph unchanged.
`FakeQuantHandle.remove` leaves the model as it was.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Iterator, Sequence

import torch
from torch import nn
from torch.nn.utils import parametrize

from e3dpsm.errors import ConfigError
from e3dpsm.layers.products import Affine, Projection
from e3dpsm.training.qat_lsq import LearnedQuantizer, RangeObserver
from e3dpsm.training.qat_sites import QuantGroup, QuantSite, linear_bias

if TYPE_CHECKING:
    from e3dpsm.training.data import WindowDataset

# Modules the INT8 graph keeps in float whatever the search decides: the Kalman fusion's
# pose embedding and the delta head feeding it (graph_groups' `fusion` recurrent group:
# `inject` stops at the first projection). The S5 recurrence has no nn.Linear of its own.
FLOAT_MODULE_PREFIXES: tuple[str, ...] = ("fusion", "pose_embed", "delta_head")
WEIGHT_QMAX = 127                              # S8 symmetric, per output channel
# ONNX Runtime's 7-bit weights (reduce_range, symmetric): levels -64..64, scale absmax / 64
# (onnxruntime.quantization.quant_utils.get_qmin_qmax_for_qType), what `quantize` gives a
# target without int8 dot-product units (quantize/static.py StaticConfig.for_target).
WEIGHT_QMAX_BY_BITS: dict[int, int] = {8: WEIGHT_QMAX, 7: 64}
RANGE_INITS: tuple[str, ...] = ("mse", "minmax", "first-batch")
# Windows of the training data the learned ranges are calibrated on before the first step.
CALIBRATION_WINDOWS = 32


@dataclass(frozen=True)
class QATConfig:
    """What is fake-quantised. `range_lr_scale`: the learned ranges' learning rate over the
    weights' (their log-scales and zero points move by about lr per Adam step, and a zero
    point needs steps of order 1 to move one level)."""

    weights: bool = True
    activations: bool = True
    range_lr_scale: float = 10.0
    # Simulate the full-integer graph (`quantize --exclude none`: the recurrent groups'
    # Conv/MatMul/Gemm too, the S5 readouts and the delta head among them) instead of the
    # default graph, which keeps them in float. The S5 readout matrices are parameters, not
    # Linear modules: their inputs are fake-quantised, their weights are not.
    full_integer: bool = False
    # Where the learned ranges start (`FakeQuantHandle.calibrate`): "mse" and "minmax" as
    # `quantize --calibration` chooses them, on calibration windows of the training data;
    # "first-batch" from the min-max of the first training batch each quantiser sees. A start
    # far from a good range costs the fine-tune its first steps, and the weights move to make
    # up for it: the first committed `small_qat` (first-batch) started 12.3 mm from its teacher
    # (benchmarks/checkpoints/small_qat/recipe.md).
    range_init: str = "mse"
    # The `quantize --float-outputs` graph simulated: outputs of these Conv/MatMul/Gemm that no
    # quantised op reads get no quantiser (quantize/outputs.py). None: "matmul" for the
    # full-integer graph (quantize's default for a fixed --exclude), "none" for the default
    # graph (its search keeps every pair). The checkpoint records it; `quantize
    # --ranges-from-checkpoint` builds the same graph unless told otherwise.
    float_outputs: str | None = None
    # The weights' bits the graph will have: 8, or 7 where `quantize` targets a CPU without
    # int8 dot-product units (its U8S8 kernels saturate with 8-bit weights there). None: the
    # bits `quantize`'s default target, this host, gets. The checkpoint records them.
    weight_bits: int | None = None

    def __post_init__(self) -> None:
        from e3dpsm.quantize.outputs import FLOAT_OUTPUTS

        if self.weight_bits is not None and self.weight_bits not in WEIGHT_QMAX_BY_BITS:
            raise ConfigError(f"QAT weight bits must be one of {sorted(WEIGHT_QMAX_BY_BITS)}, got {self.weight_bits}")
        if self.range_init not in RANGE_INITS:
            raise ConfigError(f"unknown QAT range start {self.range_init!r}; choose from {list(RANGE_INITS)}")
        if self.float_outputs is not None and self.float_outputs not in FLOAT_OUTPUTS:
            raise ConfigError(f"unknown QAT float outputs {self.float_outputs!r}; choose from {list(FLOAT_OUTPUTS)}")

    @property
    def simulated_weight_bits(self) -> int:
        if self.weight_bits is not None:
            return self.weight_bits
        from e3dpsm.quantize.static import saturates_u8s8
        from e3dpsm.utils.isa import detect_isa

        return 7 if saturates_u8s8(detect_isa().kind) else 8

    @property
    def simulated_float_outputs(self) -> str:
        if self.float_outputs is not None:
            return self.float_outputs
        return "matmul" if self.full_integer else "none"


def check_qat_flags(qat: bool, full_integer: bool) -> None:
    """The one refusal `train` and `distill` share: --qat-full-integer only picks the graph
    --qat simulates."""
    if full_integer and not qat:
        raise ConfigError("--qat-full-integer says which graph --qat simulates: add --qat")


def fake_quantize_weight(weight: torch.Tensor, qmax: int = WEIGHT_QMAX) -> torch.Tensor:
    """Symmetric per output channel (axis 0) on levels -qmax..qmax, zero point 0; gradients
    pass straight through inside the range."""
    absmax = weight.detach().abs().flatten(1).amax(dim=1).clamp_min(1e-12)
    scale = (absmax / qmax).to(torch.float32)
    zero = torch.zeros_like(scale, dtype=torch.int32)
    return torch.fake_quantize_per_channel_affine(weight, scale, zero, 0, -qmax, qmax)


def freeze_batchnorm_stats(model: nn.Module) -> int:
    """Put every BatchNorm in eval mode (running statistics used, not updated) while the rest
    trains; returns how many. Its affine parameters still learn."""
    frozen = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    for module in frozen:
        module.eval()
    return len(frozen)


class _WeightFakeQuant(nn.Module):
    def __init__(self, qmax: int) -> None:
        super().__init__()
        self.qmax = qmax

    def forward(self, weight: torch.Tensor) -> torch.Tensor:
        return fake_quantize_weight(weight, self.qmax)


def quantised_modules(model: nn.Module, full_integer: bool = False) -> list[tuple[str, nn.Module]]:
    """(name, module) of every Conv2d / Linear that the INT8 graph quantises (with
    `full_integer`, every one)."""
    floats = () if full_integer else FLOAT_MODULE_PREFIXES
    return [(name, module) for name, module in model.named_modules()
            if isinstance(module, (nn.Conv2d, nn.Linear))
            and not any(name == p or name.startswith(p + ".") for p in floats)]


def quantised_projections(model: nn.Module, weight_groups: Sequence[QuantGroup]) -> list[tuple[str, nn.Module]]:
    """(name, module) of every `Projection` or `Affine` (layers/products.py: S5 drives and
    readouts, the deformable offsets) whose weight the INT8 graph quantises (S8 per output channel, as an
    initializer): `weight_groups` matched them by value (qat_ranges.match_weights)."""
    sites = {QuantSite.parse(key).module for group in weight_groups for key in group.sites}
    return [(name, module) for name, module in model.named_modules()
            if isinstance(module, (Projection, Affine)) and name in sites]


class FakeQuantHandle:
    """The hooks, weight parametrisations and learned quantisers one `attach_fake_quant`
    call added. `groups`: the graph's quantised tensors matched to sites (qat_sites)."""

    def __init__(self, model: nn.Module, config: QATConfig, groups: Sequence[QuantGroup] = ()) -> None:
        self.model, self.config = model, config
        self.modules = quantised_modules(model, config.full_integer)
        self.groups = [g for g in groups if not g.is_weight]
        self.quantizers = nn.ModuleList(LearnedQuantizer() for _ in self.groups)
        self.projections = quantised_projections(model, [g for g in groups if g.is_weight])
        self._hooks: list[torch.utils.hooks.RemovableHandle] = []
        self._weight_hooks: list[torch.utils.hooks.RemovableHandle] = []
        self._weights_attached = False
        self.weight_bits = config.simulated_weight_bits  # resolved once: the host does not change

    def parameters(self) -> list[nn.Parameter]:
        """The learned ranges (an optimizer trains them beside the model's parameters)."""
        return list(self.quantizers.parameters())

    def _attach_weights(self) -> None:
        if self.config.weights and not self._weights_attached:
            qmax = WEIGHT_QMAX_BY_BITS[self.weight_bits]
            for _, module in self.modules:
                parametrize.register_parametrization(module, "weight", _WeightFakeQuant(qmax))
            for _, module in self.projections:  # the weight is an argument, not a parameter
                self._weight_hooks.append(module.register_forward_pre_hook(
                    lambda mod, args: (args[0], fake_quantize_weight(args[1], qmax), *args[2:])))
            self._weights_attached = True

    def _detach_weights(self) -> None:
        if self._weights_attached:
            for _, module in self.modules:
                # leave_parametrized=False puts the original Parameter object back, so an
                # optimizer built on the parameters keeps tracking the same tensors.
                parametrize.remove_parametrizations(module, "weight", leave_parametrized=False)
            for hook in self._weight_hooks:
                hook.remove()
            self._weight_hooks.clear()
            self._weights_attached = False

    def _attach_hooks(self) -> None:
        if not self.config.activations:
            return
        modules = dict(self.model.named_modules())
        for group, quantizer in zip(self.groups, self.quantizers):
            for key in group.sites:
                site = QuantSite.parse(key)
                module = modules[site.module]
                if site.kind == "in":
                    def before(mod: nn.Module, args: tuple, q: LearnedQuantizer = quantizer) -> tuple:
                        return (q(args[0]), *args[1:])
                    self._hooks.append(module.register_forward_pre_hook(before))
                elif site.kind == "in1":  # a product's second activation (layers/products.py MatMul)
                    def second(mod: nn.Module, args: tuple, q: LearnedQuantizer = quantizer) -> tuple:
                        return (args[0], q(args[1]), *args[2:])
                    self._hooks.append(module.register_forward_pre_hook(second))
                elif site.kind == "out":
                    def after(mod: nn.Module, args: tuple, out: torch.Tensor, q: LearnedQuantizer = quantizer):
                        return q(out)
                    self._hooks.append(module.register_forward_hook(after))
                else:  # "prebias": the graph's MatMul output, before the Add of the bias
                    def prebias(mod: nn.Module, args: tuple, out: torch.Tensor, q: LearnedQuantizer = quantizer):
                        bias = linear_bias(mod, args)
                        return q(out - bias) + bias
                    self._hooks.append(module.register_forward_hook(prebias))

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

    def calibrate(self, run: Callable[[], None], rule: str = "mse") -> int:
        """Start every learned range from calibration data: `run()` (called twice) runs the
        model over the same calibration windows; the quantisers record their inputs, the
        first time their min-max, the second a histogram on it, and take the range
        `quantize --calibration <rule>` would choose from it (quantize/ranges.py). Returns
        how many quantisers saw values (the others start from their first training batch)."""
        from e3dpsm.quantize.ranges import HISTOGRAM_BINS, Histogram, choose_range

        if rule not in ("mse", "minmax"):
            raise ConfigError(f"QAT ranges calibrate by 'mse' or 'minmax', not {rule!r}")
        observers = [RangeObserver() for _ in self.quantizers]
        for quantizer, observer in zip(self.quantizers, observers):
            quantizer.observer = observer
        try:
            with torch.no_grad():
                run()
                if rule == "mse":
                    for observer in observers:
                        observer.start_histogram(HISTOGRAM_BINS)
                    run()
        finally:
            for quantizer in self.quantizers:
                quantizer.observer = None
        calibrated = 0
        for quantizer, observer in zip(self.quantizers, observers):
            if not observer.high > observer.low:
                continue  # never reached, or constant (the fusion's all-zero first pose)
            if rule == "mse" and observer.counts is not None:
                chosen = choose_range(Histogram(observer.counts.numpy(), observer.low, observer.high))
                quantizer.init_from_range(chosen.low, chosen.high)
            else:
                quantizer.init_from_range(observer.low, observer.high)
            calibrated += 1
        return calibrated

    def ranges_payload(self) -> dict:
        """The checkpoint's `qat_ranges`: per learned quantiser its sites, the graph tensors
        it matched and its (scale, zero point) as the forward pass applies them."""
        from e3dpsm.training.qat_ranges import ranges_payload

        done = [(g, q) for g, q in zip(self.groups, self.quantizers) if bool(q.initialised)]
        payload = ranges_payload([(g, *q.qparams()) for g, q in done], self.config.simulated_float_outputs,
                                 self.weight_bits)
        for entry, (_, q) in zip(payload["quantizers"], done):
            entry["log_scale"] = float(q.log_scale.detach())  # for an exact resume
        return payload

    def load_ranges(self, payload: dict) -> int:
        """Restore learned quantisers from a checkpoint's `qat_ranges` (matched by site);
        returns how many were restored."""
        by_site = {s: q for q in payload.get("quantizers", []) for s in q["sites"]}
        restored = 0
        for group, quantizer in zip(self.groups, self.quantizers):
            hit = next((by_site[s] for s in group.sites if s in by_site), None)
            if hit is not None:
                quantizer.set_qparams(float(hit["scale"]), int(hit["zero_point"]))
                if "log_scale" in hit:
                    with torch.no_grad():
                        quantizer.log_scale.fill_(float(hit["log_scale"]))
                restored += 1
        return restored


def calibrate_on_windows(handle: FakeQuantHandle, model: nn.Module, dataset: "WindowDataset", count: int,
                         window_ms: float, causal: bool, rule: str) -> int:
    """`handle.calibrate` on `count` windows spread evenly over `dataset`, each run from the
    initial state as training runs it (eval mode: BatchNorm on its running statistics, which
    QAT keeps fixed). Returns how many quantisers were calibrated."""
    import numpy as np

    if count < 1:
        raise ConfigError(f"QAT range calibration needs at least 1 window, got {count}")
    indices = np.unique(np.linspace(0, len(dataset) - 1, count).round().astype(int))
    device = next(model.parameters()).device
    was_training = model.training

    def run() -> None:
        for index in indices:
            model.forward_sequence(dataset[int(index)]["lnes"][None].to(device), causal=causal, window_ms=window_ms)

    model.eval()
    try:
        return handle.calibrate(run, rule)
    finally:
        model.train(was_training)


def attach_fake_quant(model: nn.Module, config: QATConfig | None = None,
                      groups: Sequence[QuantGroup] | None = None) -> FakeQuantHandle:
    """Fake-quantise `model` in place as its INT8 graph quantises it; returns the handle
    that removes it again. `groups` (None: found by exporting the model, qat_ranges.qat_plan)
    name the graph's quantised tensors and their torch sites."""
    config = config or QATConfig()
    if groups is None and config.activations:
        from e3dpsm.training.qat_ranges import qat_plan

        groups = qat_plan(model, full_integer=config.full_integer, float_outputs=config.simulated_float_outputs)
    return FakeQuantHandle(model, config, groups or ()).attach()
