"""Which channels of a unit to keep: a magnitude criterion on the trained weights.

A channel's importance is the size of what it can add to the unit's output, the norm of
its outgoing weights times the scale of the activation that feeds them:

    residual hidden c   |gamma_c| + |beta_c| of norm2 (the BN scale and shift before SiLU)
                        x ||conv2.weight[:, c]||
    GEGLU hidden c      ||W_in[c]|| * ||W_in[H + c]|| (value and gate rows)
                        x ||W_out[:, c]||
    S5 mode p           ||B_p|| x (||C[:, p]|| + ||C_b[:, p]||) (complex norms)
    decoder FFN c       ||linear1.weight[c]|| x ||linear2.weight[:, c]||

Which units to cut, and how far, is not decided here but by the measured damage of each cut
per millisecond (or MAC) it saves (compress/plan.py).
"""
from __future__ import annotations

import torch

from e3dpsm.compress.units import ATTN_FF, DECODER_FFN, RES, SSM_FF, SSM_MODES, Unit
from e3dpsm.models import E3DPSM


def _module(model: E3DPSM, path: str) -> torch.nn.Module:
    return model.get_submodule(path)


def _geglu_scores(ff: torch.nn.Module) -> torch.Tensor:
    hidden = ff.proj_out.weight.shape[1]
    w_in = ff.proj_in.weight
    return w_in[:hidden].norm(dim=1) * w_in[hidden:].norm(dim=1) * ff.proj_out.weight.norm(dim=0)


@torch.no_grad()
def channel_scores(model: E3DPSM, unit: Unit, layer: int | None = None) -> torch.Tensor:
    """One score per channel of `unit` (higher: keep). `layer` picks the decoder layer."""
    if unit.kind == RES:
        block = _module(model, unit.name)
        scale = block.norm2.weight.abs() + block.norm2.bias.abs()
        return scale * block.conv2.weight.transpose(0, 1).flatten(1).norm(dim=1)
    if unit.kind in (ATTN_FF, SSM_FF):
        return _geglu_scores(_module(model, unit.name))
    if unit.kind == SSM_MODES:
        s5 = _module(model, unit.name)
        b = torch.sqrt(s5.b_re.pow(2) + s5.b_im.pow(2)).norm(dim=1)
        c = torch.sqrt(s5.c_re.pow(2) + s5.c_im.pow(2)).norm(dim=0)
        if hasattr(s5, "cb_re"):
            c = c + torch.sqrt(s5.cb_re.pow(2) + s5.cb_im.pow(2)).norm(dim=0)
        return b * c
    if unit.kind == DECODER_FFN:
        lay = model.decoder.layers[0 if layer is None else layer]
        return lay.linear1.weight.norm(dim=1) * lay.linear2.weight.norm(dim=0)
    raise ValueError(f"unit {unit.name} ({unit.kind}) has no channels to rank")


def keep_top(model: E3DPSM, unit: Unit, width: int, layer: int | None = None) -> list[int]:
    """Indices of the `width` highest-scoring channels, ascending."""
    if width <= 0:
        return []
    scores = channel_scores(model, unit, layer)
    return sorted(torch.topk(scores, width).indices.tolist())


def keep_lists(model: E3DPSM, units: list[Unit], widths: dict[str, int]) -> dict[str, list[int]]:
    """Surgery keep lists for new unit widths (compress/surgery.prune_model's input)."""
    by_name = {u.name: u for u in units}
    keep: dict[str, list[int]] = {}
    for name, width in widths.items():
        unit = by_name[name]
        if unit.kind == DECODER_FFN:
            for layer in range(model.config.decoder_layers):
                keep[f"decoder.layers.{layer}.ffn"] = keep_top(model, unit, width, layer)
        elif unit.kind in (RES, ATTN_FF, SSM_FF, SSM_MODES):
            keep[name] = keep_top(model, unit, width)
        else:  # attention block: whole or nothing
            keep[name] = [0] if width else []
    return keep
