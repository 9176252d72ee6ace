"""Joint-query decoder: J learned queries read the deepest-stage tokens through a standard
post-norm transformer decoder (Vaswani et al. 2017), no positional encoding (FACTS section 3)."""
from __future__ import annotations

import torch
from torch import nn


class JointQueryDecoder(nn.Module):
    def __init__(self, dim: int, num_joints: int, layers: int, heads: int, ffn: int) -> None:
        super().__init__()
        self.queries = nn.Parameter(torch.randn(num_joints, dim) * 0.02)
        layer = nn.TransformerDecoderLayer(
            dim, heads, ffn, dropout=0.0, activation="gelu", batch_first=True, norm_first=False
        )
        self.decoder = nn.TransformerDecoder(layer, layers)

    def forward(self, memory: torch.Tensor) -> torch.Tensor:
        """memory: [N, tokens, dim] -> joint features [N, J, dim]."""
        queries = self.queries.unsqueeze(0).expand(memory.shape[0], -1, -1)
        return self.decoder(queries, memory)
