"""Where the INT8 graph quantises, in PyTorch terms: torch "sites" matched to ONNX tensors.

The QDQ graph puts one QuantizeLinear on each activation tensor a quantised Conv / MatMul /
Gemm reads or writes. Those tensors carry optimiser-made names (`_v_2620`, `/stem/stem.0/
Conv_output_0`), and the graph is not the module tree: ONNX Runtime folds BatchNorm into the
Conv before it, a 3-D Linear becomes MatMul + Add (the Q sits between them, before the
bias), a 2-D one a Gemm between Reshapes (a Q on each side of the Reshape). Names cannot
say which module a tensor belongs to, so values do: one step of the PyTorch model and of the
graph on the same inputs, and a tensor matches a site when both hold the same numbers.

Sites: every leaf module's first input (`name:in`), its output (`name:out`), for a Linear
with a bias its output before the bias (`name:prebias`), and for a product of two
activations (layers/products.py `MatMul`: attention scores and mixing) its second input
(`name:in1`). A `Projection`'s weight is a site too (`name:weight`), matched to the graph's
quantised weight initializers: the graph rounds it where it quantises that MatMul. Values are compared sorted, so a
reshape or transpose between the two is no obstacle (per-tensor quantisation does not care
about layout). Matches form a bipartite graph; each connected component is one quantiser:
the same learned (scale, zero point) for all its ONNX tensors (a Gemm's output and the
Reshape after it hold the same numbers, so one range serves both), applied at all its torch
sites (quantising twice with the same range is the identity the second time).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import torch
from torch import nn

from e3dpsm.layers.products import Affine, MatMul, Projection

# Relative tolerance of a value match: the graph's fused ops (BatchNorm folded into Conv)
# move values by float32 round-off, far below what separates two different tensors.
MATCH_RTOL = 1e-4
# Tensors with fewer distinct values than this are not matched (a zero or constant tensor
# would match any other of its size).
MIN_DISTINCT = 8


@dataclass(frozen=True)
class QuantSite:
    """One place in the PyTorch model: a leaf module's input, output or pre-bias output."""

    module: str
    kind: str  # "in", "in1", "out", "prebias", "weight"

    @property
    def is_weight(self) -> bool:
        return self.kind == "weight"

    @property
    def key(self) -> str:
        return f"{self.module}:{self.kind}"

    @classmethod
    def parse(cls, key: str) -> "QuantSite":
        module, _, kind = key.rpartition(":")
        return cls(module, kind)


@dataclass(frozen=True)
class QuantGroup:
    """ONNX tensors and torch sites that hold the same numbers: one quantiser."""

    tensors: tuple[str, ...]
    sites: tuple[str, ...]

    @property
    def is_weight(self) -> bool:
        """Weights (initializers and `Projection` weight arguments), not activations."""
        return all(QuantSite.parse(s).is_weight for s in self.sites)


def linear_bias(module: nn.Module, args: tuple) -> torch.Tensor | None:
    """The bias a Linear (its parameter) or an `Affine` (its third argument) adds after the
    MatMul whose output the graph quantises; None for anything else."""
    if isinstance(module, nn.Linear):
        return module.bias
    if isinstance(module, Affine):
        return args[2]
    return None


def leaf_modules(model: nn.Module) -> list[tuple[str, nn.Module]]:
    return [(name, m) for name, m in model.named_modules() if name and not any(True for _ in m.children())]


@torch.no_grad()
def capture_sites(model: nn.Module, feed: Mapping[str, np.ndarray], frame_input: str = "lnes",
                  window_input: str = "window_ms") -> dict[str, np.ndarray]:
    """Every site's value for one `model.step` on an ONNX-style feed (frame, window, states
    under their graph input names). Modules called more than once in the step are left out:
    their sites would name more than one tensor."""
    specs = model.state_spec()
    state = {s.name: torch.from_numpy(np.asarray(feed[s.input_name])) for s in specs}
    lnes = torch.from_numpy(np.asarray(feed[frame_input]))
    window = torch.from_numpy(np.asarray(feed[window_input]))
    values: dict[str, np.ndarray] = {}
    calls: dict[str, int] = {}
    hooks = []

    def record(name: str, module: nn.Module):
        def hook(mod, args, output):
            calls[name] = calls.get(name, 0) + 1
            if args and isinstance(args[0], torch.Tensor) and args[0].is_floating_point():
                values[f"{name}:in"] = args[0].detach().numpy().copy()
            if isinstance(mod, MatMul):
                values[f"{name}:in1"] = args[1].detach().numpy().copy()
            if isinstance(mod, (Projection, Affine)):  # the weight, an argument (matched to initializers)
                values[f"{name}:weight"] = args[1].detach().numpy().copy()
            if isinstance(output, torch.Tensor) and output.is_floating_point():
                values[f"{name}:out"] = output.detach().numpy().copy()
                bias = linear_bias(mod, args)
                if bias is not None:
                    values[f"{name}:prebias"] = (output - bias).detach().numpy().copy()
        return hook

    for name, module in leaf_modules(model):
        hooks.append(module.register_forward_hook(record(name, module)))
    was_training = model.training
    model.eval()
    try:
        model.step(lnes, state, window)
    finally:
        model.train(was_training)
        for h in hooks:
            h.remove()
    repeated = {n for n, c in calls.items() if c > 1}
    return {k: v for k, v in values.items() if QuantSite.parse(k).module not in repeated}


def _fingerprint(x: np.ndarray) -> np.ndarray | None:
    flat = np.sort(np.asarray(x, dtype=np.float64).ravel())
    if flat.size < MIN_DISTINCT or len(np.unique(flat[:: max(1, flat.size // 4096)])) < MIN_DISTINCT:
        return None
    return flat


def _same(a: np.ndarray, b: np.ndarray, rtol: float) -> bool:
    scale = max(float(np.abs(a).max()), float(np.abs(b).max()), 1e-12)
    return float(np.abs(a - b).max()) <= rtol * scale


def match_groups(tensor_values: Mapping[str, np.ndarray], site_values: Mapping[str, np.ndarray],
                 rtol: float = MATCH_RTOL) -> list[QuantGroup]:
    """Connected components of the value matches between ONNX tensors and torch sites
    (module doc). Tensors that match no site are in no group."""
    sites_by_size: dict[int, list[tuple[str, np.ndarray]]] = {}
    for key, value in site_values.items():
        fp = _fingerprint(value)
        if fp is not None:
            sites_by_size.setdefault(fp.size, []).append((key, fp))
    parent: dict[str, str] = {}

    def find(x: str) -> str:
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    matched: set[str] = set()
    for name, value in tensor_values.items():
        fp = _fingerprint(value)
        if fp is None:
            continue
        for key, site_fp in sites_by_size.get(fp.size, []):
            if _same(fp, site_fp, rtol):
                parent[find("t:" + name)] = find("s:" + key)
                matched.add("t:" + name)
    components: dict[str, tuple[list[str], list[str]]] = {}
    for node in matched | {n for n in parent if n.startswith("s:")}:
        root = find(node)
        tensors, sites = components.setdefault(root, ([], []))
        (tensors if node.startswith("t:") else sites).append(node[2:])
    groups = [QuantGroup(tuple(sorted(t)), tuple(sorted(s))) for t, s in components.values() if t and s]
    return sorted(groups, key=lambda g: g.tensors)
