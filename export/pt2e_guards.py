"""Graph rewrites that keep PT2E quantisation (torchao's `prepare_pt2e`) from changing what
the float step computes, applied to the exported step before it is prepared.

`prepare_pt2e` folds every BatchNorm that reads a convolution into that convolution
(`torchao.quantization.pt2e.utils._fuse_conv_bn_`, torchao 0.18) without looking at the
convolution's other users. In this model's pre-activation residual blocks a stage's `down`
convolution feeds both the next block's first BatchNorm and that block's shortcut, so the
fold hands the shortcut the normalised tensor: on the trained `small` it moved the float
poses by 112-185 mm before a single value was quantised. Such a BatchNorm becomes an
explicit per-channel scale and shift here, which nothing folds; a BatchNorm whose
convolution has no other reader is left to the fold, which is exact there.
"""
from __future__ import annotations

import operator

import torch

_BATCH_NORMS = (torch.ops.aten.batch_norm.default, torch.ops.aten._native_batch_norm_legit_no_training.default)
_CONVOLUTIONS = (torch.ops.aten.conv1d.default, torch.ops.aten.conv2d.default, torch.ops.aten.conv3d.default,
                 torch.ops.aten.convolution.default)


def _constant(gm: torch.fx.GraphModule, node: torch.fx.Node) -> torch.Tensor:
    if not (isinstance(node, torch.fx.Node) and node.op == "get_attr"):
        raise ValueError(f"BatchNorm statistic {node} is not a constant of the graph: is the model in eval mode?")
    value = gm
    for part in str(node.target).split("."):
        value = getattr(value, part)
    return value.detach()


def _eps(node: torch.fx.Node) -> float:
    # aten.batch_norm: (input, weight, bias, mean, var, training, momentum, eps, cudnn_enabled);
    # _native_batch_norm_legit_no_training: (input, weight, bias, mean, var, momentum, eps).
    return float(node.args[7] if node.target == torch.ops.aten.batch_norm.default else node.args[6])


def unfoldable_batch_norms(gm: torch.fx.GraphModule) -> list[torch.fx.Node]:
    """BatchNorms that read a convolution which something else reads too."""
    return [n for n in gm.graph.nodes
            if n.op == "call_function" and n.target in _BATCH_NORMS
            and isinstance(n.args[0], torch.fx.Node) and n.args[0].op == "call_function"
            and n.args[0].target in _CONVOLUTIONS and len(n.args[0].users) > 1]


def explicit_shared_batch_norms(gm: torch.fx.GraphModule) -> int:
    """Rewrite each of `unfoldable_batch_norms(gm)` as `x * scale + shift` (eval statistics),
    in place; returns how many were rewritten."""
    rewritten = unfoldable_batch_norms(gm)
    for index, node in enumerate(rewritten):
        source, weight, bias, mean, var = node.args[:5]
        gamma = _constant(gm, weight) if weight is not None else None
        beta = _constant(gm, bias) if bias is not None else None
        running_mean, running_var = _constant(gm, mean), _constant(gm, var)
        scale = torch.rsqrt(running_var + _eps(node))
        if gamma is not None:
            scale = scale * gamma
        shift = -running_mean * scale + (beta if beta is not None else 0.0)
        shape = (1, -1) + (1,) * (source.meta["val"].dim() - 2)
        names = []
        for kind, value in (("scale", scale), ("shift", shift)):
            name = f"_explicit_batch_norm_{index}_{kind}"
            gm.register_buffer(name, value.reshape(shape).contiguous())
            names.append(name)
        with gm.graph.inserting_before(node):
            scale_node = gm.graph.get_attr(names[0])
            shift_node = gm.graph.get_attr(names[1])
            scaled = gm.graph.call_function(torch.ops.aten.mul.Tensor, (source, scale_node))
            affine = gm.graph.call_function(torch.ops.aten.add.Tensor, (scaled, shift_node))
        for new_node in (scaled, affine):  # the module path the quantizer's scope filter reads
            new_node.meta.update({k: v for k, v in node.meta.items() if k in ("nn_module_stack", "stack_trace")})
        if node.target == torch.ops.aten.batch_norm.default:
            node.replace_all_uses_with(affine)
        else:  # returns (out, mean, invstd): only getitem 0 is read in eval mode
            for user in list(node.users):
                if user.target is not operator.getitem or user.args[1] != 0:
                    raise ValueError(f"{node} has a reader of its saved statistics; cannot rewrite it")
                user.replace_all_uses_with(affine)
    gm.graph.eliminate_dead_code()  # the BatchNorms (and getitems) nothing reads now
    gm.recompile()
    return len(rewritten)
