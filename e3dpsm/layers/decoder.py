"""Joint-query decoder: J learned queries read the deepest-stage tokens through a standard
post-norm transformer decoder (Vaswani et al. 2017), no positional encoding (paper Sec. 4.1,
Eq. 7).

Written out rather than taken from `nn.TransformerDecoder`, whose inference fast path
(`_native_multi_head_attention`) has no ONNX export; the parameter count is the same
(packed q/k/v projections, as in `nn.MultiheadAttention`).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from e3dpsm.layers.products import MatMul


class MultiHeadAttention(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads, self.head_dim = heads, dim // heads
        self.q_proj = nn.Linear(dim, dim)
        self.kv_proj = nn.Linear(dim, 2 * dim)
        self.out_proj = nn.Linear(dim, dim)
        # Modules (no parameters) so that QAT reaches the scores, k, v and the softmaxed
        # weights, which the INT8 graph quantises as MatMul inputs and outputs.
        self.scores, self.mix = MatMul(), MatMul()

    def _split(self, x: torch.Tensor) -> torch.Tensor:
        n, length, _ = x.shape
        return x.view(n, length, self.heads, self.head_dim).transpose(1, 2)

    def forward(self, query: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        q = self._split(self.q_proj(query))
        k, v = (self._split(t) for t in self.kv_proj(context).chunk(2, dim=-1))
        attn = (self.scores(q, k.transpose(-2, -1)) * self.head_dim**-0.5).softmax(dim=-1)
        out = self.mix(attn, v).transpose(1, 2).reshape(query.shape)
        return self.out_proj(out)


class DecoderLayer(nn.Module):
    """Post-norm: x = LN(x + SelfAttn(x)); x = LN(x + CrossAttn(x, mem)); x = LN(x + FF(x))."""

    def __init__(self, dim: int, heads: int, ffn: int) -> None:
        super().__init__()
        self.self_attn = MultiHeadAttention(dim, heads)
        self.cross_attn = MultiHeadAttention(dim, heads)
        self.linear1, self.linear2 = nn.Linear(dim, ffn), nn.Linear(ffn, dim)
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(dim), nn.LayerNorm(dim), nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        x = self.norm1(x + self.self_attn(x, x))
        x = self.norm2(x + self.cross_attn(x, memory))
        return self.norm3(x + self.linear2(F.gelu(self.linear1(x))))


class JointQueryDecoder(nn.Module):
    def __init__(self, dim: int, num_joints: int, layers: int, heads: int, ffn: int) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"decoder width {dim} is not divisible by {heads} heads")
        self.queries = nn.Parameter(torch.randn(num_joints, dim))  # standard normal, as released
        self.layers = nn.ModuleList(DecoderLayer(dim, heads, ffn) for _ in range(layers))

    def forward(self, memory: torch.Tensor) -> torch.Tensor:
        """memory: [N, tokens, dim] -> joint features [N, J, dim]."""
        x = self.queries.unsqueeze(0).expand(memory.shape[0], -1, -1)
        for layer in self.layers:
            x = layer(x, memory)
        return x
