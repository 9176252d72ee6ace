"""Single-level deformable attention (Zhu et al., Deformable DETR, ICLR 2021) through
bilinear grid sampling, so it exports as the standard ONNX GridSample op (opset >= 16).

Two sampling layouts of the same weights:
- "2d" (the paper): the tokens form their h x w map and each token has its own 2-D
  reference point, initialised on the uniform grid of token centres and learned;
- "1d" (the released code): the h*w tokens form one (h*w) x 1 column, and every reference
  point is the fixed centre (0.5, 0.5) (docs/model.md#citations, Deformable attention).

The block wiring is the release's in both layouts (its `BasicTransformerBlock` around an
mmcv `MultiScaleDeformableAttention`): an outer value and output projection around mmcv's
own value and output projections, and mmcv's identity term (its query) added inside.

Three samplers of the same sum: "grid_sample" (the literal form: the reference and
training), "gather" (layers/gather_sampling.py: channels-last corner gathers and one weighted
MatMul, no GridSample) and "deform_conv" (layers/deform_conv_sampling.py: one ONNX DeformConv
node, opset >= 19, fed channels first). `export_attention_form` switches a model to an
export sampler with the block's chained projections folded (`e3dpsm export
--attention-form`); each equals the literal form to float32 round-off
(tests/test_deformable_export.py).
"""
from __future__ import annotations

import contextlib
import math
from typing import Iterator

import torch
import torch.nn.functional as F
from torch import nn

from e3dpsm.layers.deform_conv_sampling import deform_conv_sample, kernel_grid
from e3dpsm.layers.feedforward import GEGLU
from e3dpsm.layers.gather_sampling import bilinear_gather, sampling_grid
from e3dpsm.layers.products import Affine

ATTENTION_LAYOUTS: tuple[str, ...] = ("2d", "1d")
SAMPLERS: tuple[str, ...] = ("grid_sample", "gather", "deform_conv")


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

    def __init__(
        self, dim: int, heads: int, points: int, height: int, width: int, layout: str = "2d",
        sampler: str = "grid_sample",
    ) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"deformable attention width {dim} is not divisible by {heads} heads")
        if layout not in ATTENTION_LAYOUTS:
            raise ValueError(f"unknown attention layout {layout!r}; choose from {ATTENTION_LAYOUTS}")
        if sampler not in SAMPLERS:
            raise ValueError(f"unknown sampler {sampler!r}; choose from {SAMPLERS}")
        self.dim, self.heads, self.points, self.layout, self.sampler = dim, heads, points, layout, sampler
        if layout == "2d":
            self.map_hw = (height, width)
            self.reference = nn.Parameter(uniform_reference_grid(height, width))
        else:
            self.map_hw = (height * width, 1)
            self.register_buffer("reference", torch.full((1, 2), 0.5), persistent=False)
        # grid_sample units per offset unit, (x, y) per slot. A buffer, not a tensor built in
        # forward: a tensor made from a Python list lives on the host, and on a GPU each step
        # would copy it over synchronously (and CUDA graph capture refuses the copy).
        map_h, map_w = self.map_hw
        self.register_buffer("offset_scale", torch.tensor([2.0 / map_w, 2.0 / map_h]).repeat(heads * points), persistent=False)
        self.sampling_offsets = nn.Linear(dim, heads * points * 2)
        # The offsets' projection with a rescaled weight, as a module: a place QAT can hook
        # (layers/products.py); `sampling_offsets` itself is never called.
        self.offset_projection = Affine()
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
        slots = self.heads * self.points
        scale = self.offset_scale
        offsets = self.offset_projection(query, self.sampling_offsets.weight * scale[:, None], self.sampling_offsets.bias * scale)
        origin = (2.0 * self.reference - 1.0).repeat(1, slots)  # [H*W or 1, slots*2], (x, y) per slot
        return offsets + origin

    def pixel_offset_projection(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(weight, bias, origin) giving the sampling points in pixel units of the sampled map
        (grid_sample's align_corners=False convention), x of every slot first, then y:
        xy = query @ weight.T + bias + origin, [.., 2 * heads * points]; origin is
        [H*W or 1, 2 * slots]. Parameter-only: constant-folded at export.

        mmcv samples at reference + offset / (W, H) in [0, 1], i.e. at pixel
        reference * (W, H) - 0.5 + offset: the offsets need no scale in pixel units.
        """
        height, width = self.map_hw
        slots = self.heads * self.points
        weight = self.sampling_offsets.weight.view(slots, 2, -1).transpose(0, 1).reshape(2 * slots, -1)
        bias = self.sampling_offsets.bias.view(slots, 2).t().reshape(2 * slots)
        centre = self.reference * self.reference.new_tensor([width, height]) - 0.5  # [H*W or 1, 2]
        origin = centre.t().repeat_interleave(slots, dim=0).t()  # [H*W or 1, 2 * slots]
        return weight, bias, origin

    def deform_conv_offset_projection(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(weight, bias, origin) giving DeformConv's offsets: channels_first(query @ weight.T +
        bias) + origin, [N, 2 * slots, H, W], (dy, dx) per (head, point) slot, the kernel's own
        grid subtracted (deform_conv_sampling). origin is [1, 2 * slots, H, W]; all three are
        parameter-only and fold at export."""
        height, width = self.map_hw
        slots = self.heads * self.points
        dim = self.sampling_offsets.in_features
        weight = self.sampling_offsets.weight.view(slots, 2, dim).flip(1).reshape(2 * slots, dim)
        bias = self.sampling_offsets.bias.view(slots, 2).flip(1).reshape(2 * slots)
        centre = self.reference * self.reference.new_tensor([width, height]) - 0.5  # [H*W or 1, (x, y)]
        centre_yx = centre.flip(-1).t().reshape(1, 2, -1, 1)  # [1, 2, H*W or 1, 1]
        centre_yx = centre_yx.reshape(1, 2, height, width) if centre.shape[0] > 1 else centre_yx
        grid = kernel_grid(self.map_hw, self.points, centre.dtype).to(centre.device).repeat(self.heads, 1, 1, 1)
        return weight, bias, (centre_yx - grid).reshape(1, 2 * slots, height, width)

    def deform_conv_tokens(self, value: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """Tokens in, tokens out around one DeformConv, which reads and writes NCHW: value
        [N, L, dim] and the softmaxed weights [N, L, heads, points] go channels first beside
        offsets [N, 2 * slots, H, W] (kernel grid subtracted); the samples come back [N, L, dim]."""
        n = value.shape[0]
        height, width = self.map_hw

        def to_map(tokens: torch.Tensor) -> torch.Tensor:
            return tokens.transpose(1, 2).reshape(n, -1, height, width)

        sampled = deform_conv_sample(to_map(value), offsets, to_map(weights.flatten(2)), self.heads)
        return sampled.flatten(2).transpose(1, 2)

    def sample(self, value: torch.Tensor, xy: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        """The attention-weighted sampling by `self.sampler`: value [N, H*W, dim] (projected),
        xy [N, L, 2 * slots] pixel coordinates (x block, then y block), logits [N, L, slots]
        -> [N, L, dim]."""
        n, num_tokens, _ = xy.shape
        heads, points, head_dim = self.heads, self.points, self.dim // self.heads
        height, width = self.map_hw
        x, y = xy.view(n, num_tokens, 2, heads, points).unbind(dim=2)
        weights = logits.view(n, num_tokens, heads, points).softmax(dim=-1)
        if self.sampler == "gather":
            value = value.view(n, value.shape[1], heads, head_dim)
            return bilinear_gather(value, self.map_hw, x, y, weights).reshape(n, num_tokens, self.dim)
        if self.sampler == "deform_conv":
            grid = kernel_grid(self.map_hw, points, xy.dtype).to(xy.device)  # [points, (row, col), H, W]
            yx = torch.stack([y, x], dim=-1).permute(0, 2, 3, 4, 1).reshape(n, heads, points, 2, height, width)
            offsets = (yx - grid).reshape(n, 2 * heads * points, height, width)
            return self.deform_conv_tokens(value, offsets, weights)
        value = value.view(n, height, width, heads, head_dim).permute(0, 3, 4, 1, 2)
        grid = sampling_grid(x, y, self.map_hw)
        grid = grid.transpose(1, 2).reshape(n * heads, num_tokens, points, 2)
        sampled = F.grid_sample(value.reshape(n * heads, head_dim, height, width), grid, mode="bilinear",
                                padding_mode="zeros", align_corners=False)
        out = (sampled * weights.transpose(1, 2).reshape(n * heads, 1, num_tokens, points)).sum(dim=-1)
        return out.view(n, self.dim, num_tokens).transpose(1, 2)

    def forward(self, query: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
        """query, value: [N, L, dim] tokens (row-major over the h x w map) -> [N, L, dim]."""
        if self.sampler != "grid_sample":
            weight, bias, origin = self.pixel_offset_projection()
            xy = self.offset_projection(query, weight, bias) + origin
            out = self.sample(self.value_proj(value), xy, self.attention_weights(query))
            return self.output_proj(out) + query
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
    """The release's spatial transformer (docs/model.md#citations, Deformable attention):
    t = proj_in(GN x); q = LN t; t = t + out_proj(attn(q, value_proj(q))); t = t + FF(LN t);
    out = x + proj_out(t), with a GEGLU feed-forward of 4x width.

    As released, a map of at most `points` tokens skips the sampling: attn(q, v) = v.

    With `fold_projections` (the export form, `export_attention_form`), the chained linear
    maps are multiplied out: every projection of q (value, offsets, attention logits and the
    identity term through the outer output projection) is one matrix product, the sampled
    values meet one folded output projection; `attn.sampler` still picks the sampler.
    """

    def __init__(
        self, channels: int, heads: int, head_dim: int, points: int, height: int, width: int,
        layout: str = "2d", groups: int = 8, ff_mult: int = 4, ff_hidden: int | None = None,
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
        self.ff = GEGLU(inner, ff_mult * inner if ff_hidden is None else ff_hidden)
        self.proj_out = nn.Conv2d(inner, channels, 1)
        self.fold_projections = False

    def _folded_attention(self, query: torch.Tensor) -> torch.Tensor:
        """attn_output_proj(attn(query, attn_value_proj(query))) with its linear maps folded:
        Wo2 (Wo1 s + bo1 + q) + bo2 = (Wo2 Wo1) s + Wo2 q + (Wo2 bo1 + bo2), and
        Wv (Wv' q + bv') + bv = (Wv Wv') q + (Wv bv' + bv). Parameter-only products fold at export."""
        attn, inner = self.attn, self.attn.dim
        value_w = attn.value_proj.weight @ self.attn_value_proj.weight
        value_b = attn.value_proj.weight @ self.attn_value_proj.bias + attn.value_proj.bias
        out_w = self.attn_output_proj.weight @ attn.output_proj.weight
        out_b = self.attn_output_proj.weight @ attn.output_proj.bias + self.attn_output_proj.bias
        slots = attn.heads * attn.points
        channels_first = attn.sampler == "deform_conv"
        offset_w, offset_b, origin = (attn.deform_conv_offset_projection() if channels_first
                                      else attn.pixel_offset_projection())
        weight = torch.cat([value_w, offset_w, attn.attention_weights.weight, self.attn_output_proj.weight])
        bias = torch.cat([value_b, offset_b, attn.attention_weights.bias, torch.zeros_like(self.attn_output_proj.bias)])
        value, offsets, logits, identity = F.linear(query, weight, bias).split([inner, 2 * slots, slots, inner], dim=-1)
        sampled = (self._deform_conv_sampling(value, offsets, logits, origin) if channels_first
                   else attn.sample(value, offsets + origin, logits))
        return F.linear(sampled, out_w, out_b) + identity

    def _deform_conv_sampling(
        self, value: torch.Tensor, offsets: torch.Tensor, logits: torch.Tensor, origin: torch.Tensor,
    ) -> torch.Tensor:
        """The folded projections' token outputs into `deform_conv_tokens`: the softmax runs
        over each head's points on the last axis in token layout (a middle-axis softmax in NCHW
        took 1.5-2.3 ms per `paper` step); the offsets go channels first and take the origin."""
        attn = self.attn
        n, num_tokens, _ = value.shape
        height, width = attn.map_hw
        weights = logits.view(n, num_tokens, attn.heads, attn.points).softmax(dim=-1)
        offsets_map = offsets.transpose(1, 2).reshape(n, -1, height, width) + origin
        return attn.deform_conv_tokens(value, offsets_map, weights)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, _, h, w = x.shape
        t = self.proj_in(self.norm(x)).flatten(2).transpose(1, 2)  # [n, h*w, inner]
        query = self.attn_norm(t)
        if self.uses_sampling and self.fold_projections:
            t = t + self._folded_attention(query)
        else:
            value = self.attn_value_proj(query)
            t = t + self.attn_output_proj(self.attn(query, value) if self.uses_sampling else value)
        t = t + self.ff(self.ff_norm(t))
        return x + self.proj_out(t.transpose(1, 2).reshape(n, -1, h, w))


@contextlib.contextmanager
def export_attention_form(
    model: nn.Module, sampler: str = "gather", fold_projections: bool = True,
) -> Iterator[nn.Module]:
    """Within the block, every deformable block of `model` runs the given sampler and
    (optionally) its folded projections; the previous settings come back on exit."""
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; choose from {SAMPLERS}")
    blocks = [m for m in model.modules() if isinstance(m, DeformableTransformerBlock)]
    saved = [(b.attn.sampler, b.fold_projections) for b in blocks]
    try:
        for block in blocks:
            block.attn.sampler = sampler
            block.fold_projections = fold_projections
        yield model
    finally:
        for block, (old_sampler, old_fold) in zip(blocks, saved):
            block.attn.sampler, block.fold_projections = old_sampler, old_fold
