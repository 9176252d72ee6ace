"""Weighted bilinear sampling of channels-last token maps by four corner gathers: the same
sum as `F.grid_sample(mode="bilinear", padding_mode="zeros", align_corners=False)` followed
by an attention-weighted sum over the sampling points, written with default-domain ONNX
ops only (Pad, Clip, Floor, Gather, MatMul and elementwise arithmetic).

Why: GridSample wants an NCHW map per head and returns one sample per point, so the
attention needs a transpose of the value map in, a Mul and ReduceSum over the points and a
transpose out. Here the value map stays [tokens, heads, head_dim]; each (token, head) takes
its points' four corner vectors from a table of 2 x 2 neighbourhoods (one row per map
position and head) with one Gather, and sums them with one batched MatMul whose weights
are the bilinear weights times the attention weights.

Zero padding without masks: the map gets a zero border (1 before, 2 after on both axes),
and sampling coordinates are clipped to [-1, size] first. A coordinate inside that range
keeps its bilinear corners and weights, corners off the map reading the zero border; one
beyond it samples only off-map corners in grid_sample (result 0) and, clipped, lands on the
border with a zero weight on its in-map neighbour (result 0, gradient 0 as well).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

_PAD_BEFORE, _PAD_AFTER = 1, 2


def sampling_grid(x: torch.Tensor, y: torch.Tensor, map_hw: tuple[int, int]) -> torch.Tensor:
    """Pixel coordinates (pixel centres at integers) -> grid_sample's align_corners=False
    grid in [-1, 1], (x, y) on a new last axis."""
    height, width = map_hw
    return torch.stack([(2.0 * x + 1.0) / width - 1.0, (2.0 * y + 1.0) / height - 1.0], dim=-1)


def corner_table(value: torch.Tensor, map_hw: tuple[int, int]) -> torch.Tensor:
    """Rows of the four bilinear corners: value [n, H*W, heads, head_dim] ->
    [n * (H+2) * heads * (W+2), 4 * head_dim], row (y, head, x) of padded coordinates holding
    the head vectors at (x, y), (x+1, y), (x, y+1), (x+1, y+1), zero off the map.

    One gather per sampling point then fetches all four corners (4x fewer, 4x longer rows
    than a gather per corner: ONNX Runtime's Gather costs mostly per row)."""
    n, _, heads, head_dim = value.shape
    height, width = map_hw
    grid = value.reshape(n, height, width, heads, head_dim).transpose(2, 3)  # [n, H, heads, W, head_dim]
    grid = F.pad(grid, (0, 0, _PAD_BEFORE, _PAD_AFTER, 0, 0, _PAD_BEFORE, _PAD_AFTER))
    top, bottom = grid[:, :-1], grid[:, 1:]
    table = torch.cat([top[..., :-1, :], top[..., 1:, :], bottom[..., :-1, :], bottom[..., 1:, :]], dim=-1)
    return table.reshape(-1, 4 * head_dim)


def bilinear_gather(
    value: torch.Tensor, map_hw: tuple[int, int], x: torch.Tensor, y: torch.Tensor, weights: torch.Tensor,
) -> torch.Tensor:
    """sum_p weights[..., p] * bilinear(value, (x[..., p], y[..., p])), zero outside the map.

    value: [n, H*W, heads, head_dim] (row-major tokens); x, y: [n, L, heads, points] pixel
    coordinates (pixel centres at integers, as grid_sample with align_corners=False);
    weights: [n, L, heads, points]. Returns [n, L, heads, head_dim].
    """
    n, _, heads, head_dim = value.shape
    height, width = map_hw
    table_w = width + _PAD_BEFORE + _PAD_AFTER - 1
    table_h = height + _PAD_BEFORE + _PAD_AFTER - 1
    rows = corner_table(value, map_hw)

    x = x.clamp(-1.0, float(width))
    y = y.clamp(-1.0, float(height))
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    # Attention weights folded into the y factors: 4 corner weights from 6 products.
    wy0, wy1 = weights * (1.0 - fy), weights * fy
    corner_weights = torch.stack([wy0 * (1.0 - fx), wy0 * fx, wy1 * (1.0 - fx), wy1 * fx], dim=-1)

    # Table row of (x0, y0), head h, batch b. Exact in float32 below 2**24 rows per batch item.
    head = torch.arange(heads, dtype=x.dtype, device=x.device).view(heads, 1) * table_w
    index = ((y0 + _PAD_BEFORE) * (heads * table_w) + (x0 + _PAD_BEFORE) + head).long()
    batch = torch.arange(n, device=x.device).view(n, 1, 1, 1) * (table_h * heads * table_w)
    index = index + batch

    num_queries, points = index.shape[1], index.shape[-1]
    gathered = rows.index_select(0, index.reshape(-1)).view(n, num_queries, heads, 4 * points, head_dim)
    return torch.matmul(corner_weights.view(n, num_queries, heads, 1, 4 * points), gathered).squeeze(-2)
