"""Count one pose update of a PyTorch E3DPSM with `torch.utils.flop_counter.FlopCounterMode`.

FlopCounterMode counts 2 x MACs of convolutions and matrix products; GridSample is added to
it as a custom formula, the recurrences by formula (profiles.flops). Work is attributed to a
module group by watching the counter's running totals while the group's modules run: forward
hooks on every module of the group, plus a wrapper around `step` methods, because the model
calls its S5 blocks through `block.step(...)`, which no forward hook sees.
"""
from __future__ import annotations

import contextlib
import copy
import functools
from collections import Counter
from typing import Any, Iterator

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from e3dpsm.profiles.flops import MODULE_GROUPS, OTHER, FlopCount, grid_sample_macs, group_of, recurrence_macs

_GRID_SAMPLER = torch.ops.aten.grid_sampler_2d


def _grid_sampler_flops(input_shape, grid_shape, *args, out_shape=None, **kwargs) -> int:
    batch, channels = input_shape[:2]
    out_h, out_w = grid_shape[1:3]
    return 2 * grid_sample_macs(batch, channels, out_h, out_w)  # FlopCounterMode's unit: 2 x MACs


class _GroupTracker:
    """Per-group, per-op FLOP totals of a FlopCounterMode run."""

    def __init__(self, counter: FlopCounterMode) -> None:
        self.counter = counter
        self.depth: Counter[str] = Counter()
        self.start: dict[str, Counter] = {}
        self.totals: dict[str, Counter] = {g: Counter() for g in MODULE_GROUPS}

    def snapshot(self) -> Counter:
        """The counter's global per-op FLOPs so far."""
        return Counter({op: int(v) for op, v in self.counter.get_flop_counts().get("Global", {}).items()})

    def enter(self, group: str) -> None:
        if self.depth[group] == 0:
            self.start[group] = self.snapshot()
        self.depth[group] += 1

    def exit(self, group: str) -> None:
        self.depth[group] -= 1
        if self.depth[group] == 0:
            self.totals[group].update(self.snapshot() - self.start.pop(group))

    @contextlib.contextmanager
    def watching(self, model: nn.Module) -> Iterator[None]:
        handles: list[Any] = []
        patched: list[nn.Module] = []
        try:
            for group, attributes in MODULE_GROUPS.items():
                for attribute in attributes:
                    root = getattr(model, attribute, None)
                    if not isinstance(root, nn.Module):
                        continue
                    for module in root.modules():
                        handles.append(module.register_forward_pre_hook(lambda *_, g=group: self.enter(g)))
                        handles.append(module.register_forward_hook(lambda *_, g=group: self.exit(g)))
                        if callable(getattr(type(module), "step", None)):
                            module.step = self._wrap(module.step, group)  # instance attribute, removed below
                            patched.append(module)
            yield
        finally:
            for handle in handles:
                handle.remove()
            for module in patched:
                del module.step

    def _wrap(self, method, group: str):
        @functools.wraps(method)
        def wrapped(*args, **kwargs):
            self.enter(group)
            try:
                return method(*args, **kwargs)
            finally:
                self.exit(group)

        return wrapped


def count_torch(model: nn.Module) -> FlopCount:
    """Per-module MACs of one `model.step` at batch 1, and parameters per module.

    The step runs on a copy of the model on the meta device: shapes only, no arithmetic, so
    counting the paper variant takes a fraction of a second and leaves `model` untouched.
    """
    cfg = model.config
    probe = copy.deepcopy(model).to("meta").requires_grad_(False)
    lnes = torch.zeros(1, cfg.in_channels, cfg.height, cfg.width, device="meta")
    state = probe.init_state(1, device="meta")
    counter = FlopCounterMode(display=False, custom_mapping={_GRID_SAMPLER: _grid_sampler_flops})
    tracker = _GroupTracker(counter)
    with torch.no_grad(), counter, tracker.watching(probe):
        probe.step(lnes, state, cfg.train_window_ms)
    total = tracker.snapshot()

    result = FlopCount("pytorch", notes=[
        "FlopCounterMode (2 x MACs of conv / mm / bmm / addmm) halved; GridSample by formula; "
        "S5 and Kalman recurrences by formula"])
    attributed: Counter = Counter()
    for group, ops in tracker.totals.items():
        attributed.update(ops)
        _add_ops(result, group, ops)
    _add_ops(result, OTHER, total - attributed)
    for group, macs in recurrence_macs(model.state_spec(), cfg.to_dict()).items():
        result.add(group, "recurrence", macs)
    for group in result.modules:
        result.modules[group].params = 0
    for name, param in model.named_parameters():
        result.modules[group_of(name.split(".")[0])].params += param.numel()
    return result


def _add_ops(result: FlopCount, group: str, ops: Counter) -> None:
    for op, flops in ops.items():
        category = "sampling" if op is _GRID_SAMPLER or str(op).startswith("aten.grid_sampler_2d") else "dense"
        result.add(group, category, flops // 2)
