"""Attention-weighted bilinear sampling as one standard ONNX `DeformConv` node (opset >= 19).

Deformable attention's sum over a head's sampling points,
    out[c, q] = sum_p w[h(c), q, p] * bilinear(value[c], point[h(c), q, p]),
is a depthwise modulated deformable convolution (DCNv2, Zhu et al., CVPR 2019) with a 1 x P
kernel of ones: one group per channel, one offset group per head, the attention weights as
the modulation mask, and the query tokens laid out as the output map. The kernel's own
sampling grid is (row q_y, column q_x + p) for output position q and kernel tap p, so the
offsets are the sampling points minus that grid; the grid is parameter-only and folds into
a constant at export.

ONNX `DeformConv` samples bilinearly in pixel units with zeros outside the map, exactly
`F.grid_sample(mode="bilinear", padding_mode="zeros", align_corners=False)` after that
function's unnormalisation; ONNX Runtime has a native CPU kernel for it, so the sampling
costs one fused op instead of GridSample plus the transposes, Mul and ReduceSum around it.

In PyTorch the function computes the literal grid_sample form (training never runs it; the
export form is what changes). Offsets follow DeformConv's channel order: for offset group g
and kernel tap p, channels 2 (g P + p) and 2 (g P + p) + 1 hold (dy, dx).
"""
from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch.onnx import symbolic_helper

from e3dpsm.layers.gather_sampling import sampling_grid

DEFORM_CONV_MIN_OPSET = 19


def kernel_grid(map_hw: tuple[int, int], points: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Where a 1 x `points` kernel (no dilation, padded on the right only) samples before its
    offsets: [points, 2, H, W] holding (row, column) = (q_y, q_x + p) for output position q."""
    height, width = map_hw
    rows = torch.arange(height, dtype=dtype).view(1, height, 1).expand(points, height, width)
    cols = torch.arange(width, dtype=dtype).view(1, 1, width) + torch.arange(points, dtype=dtype).view(points, 1, 1)
    cols = cols.expand(points, height, width)
    return torch.stack([rows, cols], dim=1)


def _grid_sample_reference(value: torch.Tensor, offsets: torch.Tensor, mask: torch.Tensor, heads: int) -> torch.Tensor:
    n, channels, height, width = value.shape
    points = mask.shape[1] // heads
    out_h, out_w = offsets.shape[-2:]
    base = kernel_grid((out_h, out_w), points, value.dtype).to(value.device)
    yx = offsets.view(n, heads, points, 2, out_h, out_w) + base  # pixel (row, column)
    x, y = yx[:, :, :, 1], yx[:, :, :, 0]
    grid = sampling_grid(x, y, (height, width))
    grid = grid.permute(0, 1, 3, 4, 2, 5).reshape(n * heads, out_h, out_w * points, 2)
    sampled = F.grid_sample(value.reshape(n * heads, channels // heads, height, width), grid,
                            mode="bilinear", padding_mode="zeros", align_corners=False)
    sampled = sampled.view(n, heads, channels // heads, out_h, out_w, points)
    weights = mask.view(n, heads, points, out_h, out_w).permute(0, 1, 3, 4, 2).unsqueeze(2)
    return (sampled * weights).sum(dim=-1).reshape(n, channels, out_h, out_w)


# Export goes through an opaque custom op so the tracer records one node (tracing the
# reference's own ops inside a torch.autograd.Function broke the legacy exporter's peephole
# pass for single-head maps). Eager code never calls it: it has no autograd formula.
@torch.library.custom_op("e3dpsm::deform_conv_sample", mutates_args=())
def _deform_conv_op(value: torch.Tensor, offsets: torch.Tensor, mask: torch.Tensor, heads: int, channels: int,
                    points: int) -> torch.Tensor:
    return _grid_sample_reference(value, offsets, mask, heads)


@_deform_conv_op.register_fake
def _(value: torch.Tensor, offsets: torch.Tensor, mask: torch.Tensor, heads: int, channels: int,
      points: int) -> torch.Tensor:
    return value.new_empty(value.shape[0], value.shape[1], offsets.shape[-2], offsets.shape[-1])


@symbolic_helper.parse_args("v", "v", "v", "i", "i", "i")
def _deform_conv_symbolic(g: Any, value: Any, offsets: Any, mask: Any, heads: int, channels: int, points: int) -> Any:
    # Channel and point counts come as ints from the trace: with a dynamic batch axis the
    # traced tensors carry no static shapes here.
    ones = g.op("Constant", value_t=torch.ones(channels, 1, 1, points))
    no_bias = g.op("Constant", value_t=torch.zeros(channels))
    return g.op("DeformConv", value, ones, offsets, no_bias, mask, group_i=channels, offset_group_i=heads,
                kernel_shape_i=[1, points], pads_i=[0, 0, 0, points - 1])


torch.onnx.register_custom_op_symbolic("e3dpsm::deform_conv_sample", _deform_conv_symbolic, DEFORM_CONV_MIN_OPSET)


def deform_conv_sample(value: torch.Tensor, offsets: torch.Tensor, mask: torch.Tensor, heads: int) -> torch.Tensor:
    """value [N, C, H, W]; offsets [N, heads * P * 2, oH, oW] in DeformConv order (see module
    docstring); mask [N, heads * P, oH, oW] (the attention weights) -> [N, C, oH, oW]."""
    if torch.onnx.is_in_onnx_export():
        return _deform_conv_op(value, offsets, mask, heads, int(value.shape[1]), int(mask.shape[1]) // heads)
    return _grid_sample_reference(value, offsets, mask, heads)
