"""Physical channel removal: a new, smaller model whose kept channels carry the old weights.

`prune_model(model, keep)` takes, per prunable unit (compress/units.py), the indices of the
channels to keep (an empty list removes a removable unit), builds the model of the smaller
config with `E3DPSM(config)` (so the result is exactly what `create_model` or
`load_checkpoint` rebuild from that config) and copies every tensor, sliced where a unit
runs through it. When the removed channels contributed nothing (their outgoing weights
zero), the pruned model computes the same function to float32 round-off
(tests/test_prune_surgery.py).
"""
from __future__ import annotations

from typing import Callable, Mapping, Sequence

import torch

from e3dpsm.compress.units import ATTN_BLOCK, ATTN_FF, DECODER_FFN, RES, SSM_FF, SSM_MODES, Unit, config_with_widths, prunable_units
from e3dpsm.models import E3DPSM

Slicer = Callable[[torch.Tensor], torch.Tensor]


def _rows(idx: torch.Tensor) -> Slicer:
    return lambda t: t.index_select(0, idx)


def _cols(idx: torch.Tensor) -> Slicer:
    return lambda t: t.index_select(1, idx)


def _geglu_rows(idx: torch.Tensor, hidden: int) -> Slicer:
    # proj_in stacks the value half and the gate half (chunk(2)): channel c is rows c and H + c.
    both = torch.cat([idx, idx + hidden])
    return lambda t: t.index_select(0, both)


def _keep_index(name: str, keep: Sequence[int], width: int) -> torch.Tensor:
    """The kept channel indices, ascending; ValueError unless distinct and within [0, width)."""
    idx = torch.as_tensor(sorted(keep), dtype=torch.long)
    if len(set(keep)) != len(keep) or (len(keep) and (idx.min() < 0 or idx.max() >= width)):
        raise ValueError(f"{name}: keep indices must be distinct, within [0, {width})")
    return idx


def unit_slicers(model: E3DPSM, unit: Unit, keep: Sequence[int]) -> dict[str, Slicer]:
    """state_dict key -> how to slice it, for every tensor the unit's channels run through."""
    idx = _keep_index(f"unit {unit.name}", keep, unit.width)
    p = unit.name
    if unit.kind == RES:
        rows = _rows(idx)
        return {f"{p}.conv1.weight": rows, f"{p}.conv1.bias": rows, f"{p}.norm2.weight": rows,
                f"{p}.norm2.bias": rows, f"{p}.norm2.running_mean": rows, f"{p}.norm2.running_var": rows,
                f"{p}.conv2.weight": _cols(idx)}
    if unit.kind in (ATTN_FF, SSM_FF):
        ff = p  # attention.{i}.ff / ssm.{s}.ff
        out = {f"{ff}.proj_in.weight": _geglu_rows(idx, unit.width), f"{ff}.proj_out.weight": _cols(idx)}
        if f"{ff}.proj_in.bias" in model.state_dict():
            out[f"{ff}.proj_in.bias"] = _geglu_rows(idx, unit.width)
        return out
    if unit.kind == SSM_MODES:
        rows, cols = _rows(idx), _cols(idx)
        out = {f"{p}.{n}": rows for n in ("log_neg_lambda_re", "lambda_im", "log_step", "b_re", "b_im")}
        out.update({f"{p}.{n}": cols for n in ("c_re", "c_im", "cb_re", "cb_im") if f"{p}.{n}" in model.state_dict()})
        return out
    if unit.kind == DECODER_FFN:
        raise ValueError("decoder.ffn is cut per layer: pass decoder.layers.{l}.ffn keep lists")
    return {}  # ATTN_BLOCK: its tensors simply do not exist in the pruned model


def prune_model(model: E3DPSM, keep: Mapping[str, Sequence[int]]) -> E3DPSM:
    """A new model without the channels not in `keep` (unit name -> kept channel indices).

    Units not named keep every channel. The decoder's feed-forward is named per layer,
    `decoder.layers.{l}.ffn`, all with the same count (one `decoder_ffn`). An attention block
    is removed by `{"attention.{i}": []}`.
    """
    cfg = model.config
    units = {u.name: u for u in prunable_units(cfg)}
    widths: dict[str, int] = {}
    decoder_keep = {k: v for k, v in keep.items() if k.startswith("decoder.layers.")}
    if decoder_keep:
        counts = {len(v) for v in decoder_keep.values()}
        if len(decoder_keep) != cfg.decoder_layers or len(counts) != 1:
            raise ValueError(f"the decoder feed-forward needs one keep list per layer ({cfg.decoder_layers}), "
                             "all of one length (decoder_ffn is one number)")
        widths["decoder.ffn"] = counts.pop()
    for name, kept in keep.items():
        if name in decoder_keep:
            continue
        if name not in units:
            raise KeyError(f"{name!r} is not a prunable unit of this model; units: {sorted(units)}")
        if units[name].kind == ATTN_BLOCK and len(kept) not in (0, 1):
            raise ValueError(f"{name}: an attention block is kept ([0]) or removed ([]) whole")
        widths[name] = len(kept)
    new_cfg = config_with_widths(cfg, widths)

    slicers: dict[str, Slicer] = {}
    for name, kept in keep.items():
        if name in decoder_keep:
            idx = _keep_index(name, kept, cfg.decoder_ffn)
            layer = name[: -len(".ffn")]
            slicers.update({f"{layer}.linear1.weight": _rows(idx), f"{layer}.linear1.bias": _rows(idx),
                            f"{layer}.linear2.weight": _cols(idx)})
        elif len(kept) > 0:
            slicers.update(unit_slicers(model, units[name], kept))

    old = model.state_dict()
    pruned = E3DPSM(new_cfg)
    new_state = {}
    for key, target in pruned.state_dict().items():
        value = old[key]
        if key in slicers:
            value = slicers[key](value)
        if value.shape != target.shape:  # a coupling this module does not know: fail loudly
            raise RuntimeError(f"surgery left {key} at {tuple(value.shape)}, the pruned model needs {tuple(target.shape)}")
        new_state[key] = value.clone()
    pruned.load_state_dict(new_state, strict=True)
    return pruned.train(model.training)
