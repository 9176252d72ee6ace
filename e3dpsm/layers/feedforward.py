"""GEGLU feed-forward (Shazeer 2020, "GLU Variants Improve Transformer")."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class GEGLU(nn.Module):
    """x -> W2 (a * GELU(g)), with [a, g] = W1 x; acts on the last axis."""

    def __init__(self, dim: int, hidden: int, bias: bool = True) -> None:
        super().__init__()
        self.proj_in = nn.Linear(dim, 2 * hidden, bias=bias)
        self.proj_out = nn.Linear(hidden, dim, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, gate = self.proj_in(x).chunk(2, dim=-1)
        return self.proj_out(a * F.gelu(gate))
