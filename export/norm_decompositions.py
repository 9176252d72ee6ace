"""LayerNorm and GroupNorm written as matrix products and elementwise ops, for backends that
take those but not the norms: ExecuTorch's XNNPACK partitioner (1.5) has no rule for
`native_layer_norm` / `native_group_norm` and leaves them on portable kernels, one
delegate boundary (and one graph break) each.

The mean over the normalised values is a product with a constant column of 1 / n, a fully
connected layer with one output that XNNPACK runs; the variance is the mean of the squared
deviations (two passes, as the norms compute it, no E[x^2] - E[x]^2 cancellation). Applied
through `ExportedProgram.run_decompositions` at export for ExecuTorch only: the model, its
training and its ONNX graph keep the native ops. Equal to them to float32 round-off
(tests/test_edge_export.py, against numpy)."""
from __future__ import annotations

import math
from typing import Sequence

import torch


def _normalise_rows(rows: torch.Tensor, eps: float) -> torch.Tensor:
    """(rows - mean) / sqrt(var + eps) of every row of a 2-D tensor, means as matmuls."""
    width = rows.shape[1]
    average = torch.full((width, 1), 1.0 / width, dtype=rows.dtype, device=rows.device)
    centred = rows - rows @ average
    return centred * torch.rsqrt((centred * centred) @ average + eps)


def layer_norm_as_matmuls(x: torch.Tensor, normalized_shape: Sequence[int], weight: torch.Tensor | None = None,
                          bias: torch.Tensor | None = None, eps: float = 1e-5, cudnn_enable: bool = True) -> torch.Tensor:
    """`aten.layer_norm` over the trailing `normalized_shape` axes."""
    width = math.prod(normalized_shape)
    y = _normalise_rows(x.reshape(-1, width), eps).reshape(x.shape)
    if weight is not None:
        y = y * weight
    if bias is not None:
        y = y + bias
    return y


def group_norm_as_matmuls(x: torch.Tensor, num_groups: int, weight: torch.Tensor | None = None,
                          bias: torch.Tensor | None = None, eps: float = 1e-5, cudnn_enable: bool = True) -> torch.Tensor:
    """`aten.group_norm` of [N, C, *spatial]: each (sample, group) is one row."""
    channels = x.shape[1]
    y = _normalise_rows(x.reshape(x.shape[0] * num_groups, -1), eps).reshape(x.shape)
    per_channel = (1, channels) + (1,) * (x.dim() - 2)
    if weight is not None:
        y = y * weight.reshape(per_channel)
    if bias is not None:
        y = y + bias.reshape(per_channel)
    return y


def norm_decompositions() -> dict:
    """The table for `ExportedProgram.run_decompositions`: these two ops, nothing else (the
    backend's partitioner decides how the rest is decomposed)."""
    aten = torch.ops.aten
    return {aten.layer_norm.default: layer_norm_as_matmuls, aten.group_norm.default: group_norm_as_matmuls}
