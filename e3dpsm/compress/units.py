"""What pruning can cut: the prunable units of a model and the config field each one sets.

A unit is one width whose channels can be removed without touching anything outside it,
because the normalisation around it is per channel (BatchNorm) or absent:

    stages.{i}.block{j}       residual block hidden width: conv1 out, norm2, conv2 in
                              (0 removes the residual branch, the shortcut stays)
    attention.{i}.ff          GEGLU hidden width of a deformable block: proj_in's value and
                              gate halves (rows c and H + c together), proj_out in
    attention.{i}             the whole deformable block (removal only: the block -> identity)
    ssm.{s}.ff                GEGLU hidden width of an S5 block (bias-free)
    ssm.{s}.s5                S5 state size P: B rows, C and C_b columns, Lambda, step; the
                              carried state [h, w, P] shrinks with it
    decoder.ffn               decoder feed-forward width, the same count in every layer
                              (`decoder_ffn` is one number), channels chosen per layer

Not cut: the stage widths (the residual stream) and the attention inner width. Both feed
LayerNorm or GroupNorm(8) statistics, so a removed channel changes every other channel's
normalisation even when it carried zeros: no cut there preserves the function, and
(measured on the trained `small`, docs/compress.md) the step time does not live there.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from e3dpsm.models.config import E3DPSMConfig

RES, ATTN_FF, ATTN_BLOCK, SSM_FF, SSM_MODES, DECODER_FFN = "res", "attn_ff", "attn_block", "ssm_ff", "ssm_modes", "decoder_ffn"


@dataclass(frozen=True)
class Unit:
    name: str  # module path prefix in the model and in the exported graph's node names
    kind: str
    stage: int | None
    block: int | None
    width: int  # current width (for ATTN_BLOCK: 1 while present)
    removable: bool  # may go to width 0 (whole branch / block gone)
    scope: str  # the node-name scope of its work in the exported graph
    # Further node-name scopes of its work (the decoder FFN's linear1/linear2 of every layer).
    more_scopes: tuple[str, ...] = ()

    @property
    def scopes(self) -> tuple[str, ...]:
        return (self.scope, *self.more_scopes)


def prunable_units(cfg: E3DPSMConfig) -> list[Unit]:
    """Every unit of a config that is still present (width > 0)."""
    units: list[Unit] = []
    for i in range(len(cfg.widths)):
        for b in range(cfg.blocks_per_stage):
            width = cfg.res_hidden_width(i, b)
            if width > 0:
                name = f"stages.{i}.block{b + 1}"
                units.append(Unit(name, RES, i, b, width, True, f"/stages.{i}/block{b + 1}/"))
        if cfg.has_attention(i):
            units.append(Unit(f"attention.{i}.ff", ATTN_FF, i, None, cfg.attn_ff_width(i), False, f"/attention.{i}/ff/"))
            units.append(Unit(f"attention.{i}", ATTN_BLOCK, i, None, 1, True, f"/attention.{i}/"))
    for s in sorted(cfg.ssm_stages):
        units.append(Unit(f"ssm.{s}.ff", SSM_FF, s, None, cfg.ssm_ff_width(s), False, f"/ssm.{s}/ff/"))
        units.append(Unit(f"ssm.{s}.s5", SSM_MODES, s, None, cfg.ssm_state_dim(s), False, f"/ssm.{s}/s5/"))
    ffn_scopes = tuple(f"/decoder/layers.{l}/{lin}/" for l in range(cfg.decoder_layers) for lin in ("linear1", "linear2"))
    units.append(Unit("decoder.ffn", DECODER_FFN, None, None, cfg.decoder_ffn, False, ffn_scopes[0], ffn_scopes[1:]))
    return units


def config_with_widths(cfg: E3DPSMConfig, widths: dict[str, int]) -> E3DPSMConfig:
    """The config with the given unit widths (unit name -> new width; ATTN_BLOCK: 0 removes).
    Every pruned field is written out in full, so the config records every width."""
    bps, stages = cfg.blocks_per_stage, sorted(cfg.ssm_stages)
    res = [cfg.res_hidden_width(i, b) for i in range(len(cfg.widths)) for b in range(bps)]
    attn_ff = [cfg.attn_ff_width(i) for i in range(len(cfg.widths))]
    removed = set(cfg.attn_removed)
    ssm_ff = [cfg.ssm_ff_width(s) for s in stages]
    modes = [cfg.ssm_state_dim(s) for s in stages]
    decoder_ffn = cfg.decoder_ffn
    by_name = {u.name: u for u in prunable_units(cfg)}
    for name, width in widths.items():
        unit = by_name.get(name)
        if unit is None:
            raise KeyError(f"{name!r} is not a prunable unit of this model; units: {sorted(by_name)}")
        if width < (0 if unit.removable else 1) or width > unit.width:
            raise ValueError(f"unit {name}: width {width} outside [{0 if unit.removable else 1}, {unit.width}]")
        if unit.kind == RES:
            res[unit.stage * bps + unit.block] = width
        elif unit.kind == ATTN_FF:
            attn_ff[unit.stage] = width
        elif unit.kind == ATTN_BLOCK and width == 0:
            removed.add(unit.stage)
        elif unit.kind == SSM_FF:
            ssm_ff[stages.index(unit.stage)] = width
        elif unit.kind == SSM_MODES:
            modes[stages.index(unit.stage)] = width
        elif unit.kind == DECODER_FFN:
            decoder_ffn = width
    overrides: dict[str, Any] = dict(
        res_hidden=tuple(res), attn_ff_hidden=tuple(attn_ff), attn_removed=tuple(sorted(removed)),
        ssm_ff_hidden=tuple(ssm_ff), ssm_state_dims=tuple(modes), decoder_ffn=decoder_ffn,
    )
    return cfg.replace(**overrides)
