"""e3dpsm/compress/units.py: the tiny's prunable units written out by hand from its config
(stage widths 8, 16, 16, 24, two residual blocks a stage, a deformable block on every stage
with a GEGLU feed-forward four times its width, S5 blocks after stages 0 and 3, one decoder
layer of feed-forward 48), and each unit's cut landing in its own config field only."""
from __future__ import annotations

import dataclasses

import pytest

import e3dpsm
from e3dpsm.compress.units import (ATTN_BLOCK, ATTN_FF, DECODER_FFN, RES, SSM_FF, SSM_MODES, Unit,
                                   config_with_widths, prunable_units)

TINY = e3dpsm.create_model("tiny").config
TINY_UNITS = [  # name, kind, stage, block, width, removable, scope
    ("stages.0.block1", RES, 0, 0, 8, True, "/stages.0/block1/"),
    ("stages.0.block2", RES, 0, 1, 8, True, "/stages.0/block2/"),
    ("attention.0.ff", ATTN_FF, 0, None, 32, False, "/attention.0/ff/"),
    ("attention.0", ATTN_BLOCK, 0, None, 1, True, "/attention.0/"),
    ("stages.1.block1", RES, 1, 0, 16, True, "/stages.1/block1/"),
    ("stages.1.block2", RES, 1, 1, 16, True, "/stages.1/block2/"),
    ("attention.1.ff", ATTN_FF, 1, None, 64, False, "/attention.1/ff/"),
    ("attention.1", ATTN_BLOCK, 1, None, 1, True, "/attention.1/"),
    ("stages.2.block1", RES, 2, 0, 16, True, "/stages.2/block1/"),
    ("stages.2.block2", RES, 2, 1, 16, True, "/stages.2/block2/"),
    ("attention.2.ff", ATTN_FF, 2, None, 64, False, "/attention.2/ff/"),
    ("attention.2", ATTN_BLOCK, 2, None, 1, True, "/attention.2/"),
    ("stages.3.block1", RES, 3, 0, 24, True, "/stages.3/block1/"),
    ("stages.3.block2", RES, 3, 1, 24, True, "/stages.3/block2/"),
    ("attention.3.ff", ATTN_FF, 3, None, 96, False, "/attention.3/ff/"),
    ("attention.3", ATTN_BLOCK, 3, None, 1, True, "/attention.3/"),
    ("ssm.0.ff", SSM_FF, 0, None, 8, False, "/ssm.0/ff/"),
    ("ssm.0.s5", SSM_MODES, 0, None, 4, False, "/ssm.0/s5/"),
    ("ssm.3.ff", SSM_FF, 3, None, 24, False, "/ssm.3/ff/"),
    ("ssm.3.s5", SSM_MODES, 3, None, 12, False, "/ssm.3/s5/"),
]


def test_the_tinys_units_by_hand() -> None:
    units = prunable_units(TINY)
    assert [(u.name, u.kind, u.stage, u.block, u.width, u.removable, u.scope) for u in units[:-1]] == TINY_UNITS
    assert all(u.more_scopes == () and u.scopes == (u.scope,) for u in units[:-1])
    decoder = units[-1]
    assert (decoder.name, decoder.kind, decoder.width, decoder.removable) == ("decoder.ffn", DECODER_FFN, 48, False)
    assert decoder.scopes == ("/decoder/layers.0/linear1/", "/decoder/layers.0/linear2/")
    two_layers = prunable_units(TINY.replace(decoder_layers=2))[-1]
    assert two_layers.scopes == tuple(f"/decoder/layers.{layer}/{linear}/" for layer in (0, 1)
                                      for linear in ("linear1", "linear2"))
    with pytest.raises(dataclasses.FrozenInstanceError):
        decoder.width = 1


BEFORE = {"res_hidden": (8, 8, 16, 16, 16, 16, 24, 24), "attn_ff_hidden": (32, 64, 64, 96), "attn_removed": (),
          "ssm_ff_hidden": (8, 24), "ssm_state_dims": (4, 12), "decoder_ffn": 48}


@pytest.mark.parametrize("widths, changed", [
    ({}, {}),
    ({"stages.1.block2": 4}, {"res_hidden": (8, 8, 16, 4, 16, 16, 24, 24)}),
    ({"stages.0.block1": 0, "stages.3.block2": 24}, {"res_hidden": (0, 8, 16, 16, 16, 16, 24, 24)}),
    ({"attention.2.ff": 16}, {"attn_ff_hidden": (32, 64, 16, 96)}),
    ({"attention.3": 0, "attention.1": 0}, {"attn_removed": (1, 3)}),
    ({"attention.1": 1}, {}),  # a block kept is no removal
    ({"ssm.3.ff": 12}, {"ssm_ff_hidden": (8, 12)}),
    ({"ssm.0.s5": 2}, {"ssm_state_dims": (2, 12)}),
    ({"decoder.ffn": 24}, {"decoder_ffn": 24}),
])
def test_each_cut_writes_its_own_field_and_every_width_in_full(widths, changed) -> None:
    cfg = config_with_widths(TINY, widths)
    assert {field: getattr(cfg, field) for field in BEFORE} == {**BEFORE, **changed}
    assert cfg.widths == TINY.widths and cfg.variant == TINY.variant


def test_cut_units_are_no_longer_units_and_a_removed_block_takes_its_feed_forward() -> None:
    cfg = config_with_widths(TINY, {"stages.0.block1": 0, "attention.2": 0})
    names = [u.name for u in prunable_units(cfg)]
    assert "stages.0.block1" not in names and "attention.2" not in names and "attention.2.ff" not in names
    assert len(names) == len(TINY_UNITS) + 1 - 3
    again = config_with_widths(cfg, {"stages.0.block2": 4})  # a pruned config prunes further
    assert again.res_hidden == (0, 4, 16, 16, 16, 16, 24, 24) and again.attn_removed == (2,)


@pytest.mark.parametrize("widths, error, message", [
    ({"stages.9.block1": 1}, KeyError, "'stages.9.block1' is not a prunable unit of this model; units: ["),
    ({"attention.0.ff": 0}, ValueError, "unit attention.0.ff: width 0 outside [1, 32]"),
    ({"ssm.0.s5": 5}, ValueError, "unit ssm.0.s5: width 5 outside [1, 4]"),
    ({"stages.0.block1": 9}, ValueError, "unit stages.0.block1: width 9 outside [0, 8]"),
    ({"stages.0.block1": -1}, ValueError, "unit stages.0.block1: width -1 outside [0, 8]"),
    ({"decoder.ffn": 0}, ValueError, "unit decoder.ffn: width 0 outside [1, 48]"),
])
def test_a_width_outside_a_units_range_or_an_unknown_unit_is_refused(widths, error, message) -> None:
    with pytest.raises(error) as info:
        config_with_widths(TINY, widths)
    assert str(info.value.args[0]).startswith(message)


def test_the_narrowest_widths_are_still_units() -> None:
    """One channel is a width: a residual block or a feed-forward cut to 1 is still there (and
    may be cut again); only 0 removes."""
    cfg = config_with_widths(TINY, {"stages.0.block1": 1, "attention.0.ff": 1, "ssm.3.s5": 1})
    widths = {u.name: u.width for u in prunable_units(cfg)}
    assert (widths["stages.0.block1"], widths["attention.0.ff"], widths["ssm.3.s5"]) == (1, 1, 1)


def test_a_unit_is_a_frozen_record_of_its_scopes() -> None:
    unit = Unit("decoder.ffn", DECODER_FFN, None, None, 8, False, "/a/", ("/b/", "/c/"))
    assert unit.scopes == ("/a/", "/b/", "/c/")
    assert Unit("x", RES, 0, 0, 8, True, "/x/").more_scopes == ()
