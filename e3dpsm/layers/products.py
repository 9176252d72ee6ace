"""Products of activations as modules of their own, with no parameters.

Quantisation-aware training finds the places the INT8 graph quantises by module
(training/qat_sites.py: a leaf module's inputs and output are "sites"). A product written
inline (`x @ w.t()`, `q @ k.transpose(-2, -1)`) has no module, so its output, and an input
that is no other module's output, would keep a calibrated range in the graph while training
simulated none. These modules give them a place; the computation and the exported graph are
the plain MatMul's, and a state dict gains no keys.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class Projection(nn.Module):
    """`x @ weight.T` for a weight the caller owns (a parameter, or one computed from
    parameters, such as a rescaled or folded matrix)."""

    def forward(self, x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        return x @ weight.t()


class MatMul(nn.Module):
    """`a @ b` for two activations (attention scores, attention-weighted values): both
    inputs are sites (`in`, `in1`)."""

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return a @ b


class Affine(nn.Module):
    """`F.linear(x, weight, bias)` for a weight and bias the caller owns (the deformable
    offsets' rescaled projection). One fused op, as before it was a module, so training
    computes what it did; its sites are a Linear's (`in`, `out`, `prebias`) and its weight."""

    def forward(self, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        return F.linear(x, weight, bias)
