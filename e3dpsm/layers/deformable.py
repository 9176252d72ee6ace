"""Single-level deformable attention (Zhu et al., Deformable DETR, ICLR 2021) through
bilinear grid sampling, so it exports as the standard ONNX GridSample op (opset >= 16).

Two sampling layouts of the same weights:
- "2d" (the paper): the tokens form their h x w map and each token has its own 2-D
  reference point, initialised on the uniform grid of token centres and learned;
- "1d" (the released code): the h*w tokens form one (h*w) x 1 column, and every reference
  point is the fixed centre (0.5, 0.5) (FACTS section 3).

The block wiring is the release's in both layouts (its `BasicTransformerBlock` around an
mmcv `MultiScaleDeformableAttention`): an outer value and output projection around mmcv's
own value and output projections, and mmcv's identity term (its query) added inside.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from e3dpsm.layers.feedforward import GEGLU

ATTENTION_LAYOUTS: tuple[str, ...] = ("2d", "1d")


def uniform_reference_grid(height: int, width: int) -> torch.Tensor:
    """Token centres in normalised [0, 1] (x, y) coordinates, row-major, shape [H*W, 2]."""
    ys = (torch.arange(height, dtype=torch.float32) + 0.5) / height
    xs = (torch.arange(width, dtype=torch.float32) + 0.5) / width
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([grid_x.reshape(-1), grid_y.reshape(-1)], dim=-1)


class DeformableAttention(nn.Module):
    """What mmcv's `MultiScaleDeformableAttention` computes for one level:
    output_proj(sample(value_proj(value), at offsets(query), weighted by softmax(query))) + query.

    `height` x `width` is the token map; the layout decides the sampled map and the
    reference points (module docstring).
    """

    def __init__(self, dim: int, heads: int, points: int, height: int, width: int, layout: str = "2d") -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"deformable attention width {dim} is not divisible by {heads} heads")
        if layout not in ATTENTION_LAYOUTS:
            raise ValueError(f"unknown attention layout {layout!r}; choose from {ATTENTION_LAYOUTS}")
        self.dim, self.heads, self.points, self.layout = dim, heads, points, layout
        if layout == "2d":
            self.map_hw = (height, width)
            self.reference = nn.Parameter(uniform_reference_grid(height, width))
        else:
            self.map_hw = (height * width, 1)
            self.register_buffer("reference", torch.full((1, 2), 0.5), persistent=False)
        self.sampling_offsets = nn.Linear(dim, heads * points * 2)
        self.attention_weights = nn.Linear(dim, heads * points)
        self.value_proj = nn.Linear(dim, dim)
        self.output_proj = nn.Linear(dim, dim)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # Deformable DETR's (and mmcv's) start: head h samples along direction 2*pi*h/heads,
        # point k at k+1 pixels, so the heads look around the reference before training.
        nn.init.zeros_(self.sampling_offsets.weight)
        angles = torch.arange(self.heads, dtype=torch.float32) * (2.0 * math.pi / self.heads)
        directions = torch.stack([angles.cos(), angles.sin()], dim=-1)
        directions = directions / directions.abs().max(dim=-1, keepdim=True).values
        scales = torch.arange(1, self.points + 1, dtype=torch.float32).view(1, -1, 1)
        with torch.no_grad():
            self.sampling_offsets.bias.copy_((directions[:, None, :] * scales).reshape(-1))
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        for proj in (self.value_proj, self.output_proj):
            nn.init.xavier_uniform_(proj.weight)
            nn.init.zeros_(proj.bias)

    def _sampling_grid(self, query: torch.Tensor) -> torch.Tensor:
        """grid_sample coordinates in [-1, 1], flat: [N, L, heads*points*2].

        mmcv samples at reference + offset / (W, H) in [0, 1] coordinates, i.e. at
        (2 * reference - 1) + offset * (2 / W, 2 / H) in grid_sample's. Folding the
        (2 / W, 2 / H) scale into the offset projection's weights and laying the reference
        out at full width leaves only parameter-only terms (constant-folded at export) and
        one Add. The literal form, broadcasting [.., 2]-sized tensors, measured 3.3 ms of a
        27.6 ms `paper` step in ONNX Runtime 1.31 (slow broadcast path for tiny trailing dims).
        """
        height, width = self.map_hw
        slots = self.heads * self.points
        scale = query.new_tensor([2.0 / width, 2.0 / height]).repeat(slots)
        offsets = F.linear(query, self.sampling_offsets.weight * scale[:, None], self.sampling_offsets.bias * scale)
        origin = (2.0 * self.reference - 1.0).repeat(1, slots)  # [H*W or 1, slots*2], (x, y) per slot
        return offsets + origin

    def forward(self, query: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
        """query, value: [N, L, dim] tokens (row-major over the h x w map) -> [N, L, dim]."""
        n, num_tokens, _ = query.shape
        heads, points, head_dim = self.heads, self.points, self.dim // self.heads
        height, width = self.map_hw
        value = self.value_proj(value).view(n, height, width, heads, head_dim)
        value = value.permute(0, 3, 4, 1, 2).reshape(n * heads, head_dim, height, width)

        grid = self._sampling_grid(query)
        grid = grid.view(n, num_tokens, heads, points, 2).permute(0, 2, 1, 3, 4).reshape(n * heads, num_tokens, points, 2)
        sampled = F.grid_sample(value, grid, mode="bilinear", padding_mode="zeros", align_corners=False)

        weights = self.attention_weights(query).view(n, num_tokens, heads, points).softmax(dim=-1)
        weights = weights.permute(0, 2, 1, 3).reshape(n * heads, 1, num_tokens, points)
        out = (sampled * weights).sum(dim=-1)  # [n*heads, head_dim, tokens]
        out = out.view(n, heads * head_dim, num_tokens).transpose(1, 2)
        return self.output_proj(out) + query


class DeformableTransformerBlock(nn.Module):
    """The release's spatial transformer (FACTS section 3):
    t = proj_in(GN x); q = LN t; t = t + out_proj(attn(q, value_proj(q))); t = t + FF(LN t);
    out = x + proj_out(t), with a GEGLU feed-forward of 4x width.

    As released, a map of at most `points` tokens skips the sampling: attn(q, v) = v.
    """

    def __init__(
        self, channels: int, heads: int, head_dim: int, points: int, height: int, width: int,
        layout: str = "2d", groups: int = 8, ff_mult: int = 4,
    ) -> None:
        super().__init__()
        inner = heads * head_dim
        self.uses_sampling = height * width > points
        self.norm = nn.GroupNorm(groups, channels)
        self.proj_in = nn.Conv2d(channels, inner, 1)
        self.attn_norm = nn.LayerNorm(inner)
        self.attn_value_proj = nn.Linear(inner, inner)
        self.attn = DeformableAttention(inner, heads, points, height, width, layout)
        self.attn_output_proj = nn.Linear(inner, inner)
        self.ff_norm = nn.LayerNorm(inner)
        self.ff = GEGLU(inner, ff_mult * inner)
        self.proj_out = nn.Conv2d(inner, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, _, h, w = x.shape
        t = self.proj_in(self.norm(x)).flatten(2).transpose(1, 2)  # [n, h*w, inner]
        query = self.attn_norm(t)
        value = self.attn_value_proj(query)
        t = t + self.attn_output_proj(self.attn(query, value) if self.uses_sampling else value)
        t = t + self.ff(self.ff_norm(t))
        return x + self.proj_out(t.transpose(1, 2).reshape(n, -1, h, w))
