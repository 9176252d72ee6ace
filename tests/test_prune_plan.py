"""A pruning round's candidates and choice (e3dpsm/compress/plan.py): the widths tried, each cut's
damage and MAC saving, and the greedy ranking, against the rules in the module's docstring and
counts written out per module."""
from __future__ import annotations

import math

import pytest
import torch

import e3dpsm
from _model_helpers import randomised_tiny
from e3dpsm.compress.latency import LatencyProfile, UnitLatency
from e3dpsm.compress.plan import (Candidate, _aligned, candidate_widths, choose, count_macs, macs_per_stage,
                                  measure_candidates, pose_distance_mm, total_macs)
from e3dpsm.compress.units import ATTN_BLOCK, ATTN_FF, RES, Unit, prunable_units


@pytest.mark.parametrize("width, shrink, align, expected", [
    (64, 0.5, 8, 32),     # a multiple of the alignment
    (60, 0.5, 8, 24),     # 30 rounded down to a multiple of 8
    (30, 0.5, 8, 8),      # 15 -> 8: never below one aligned group
    (10, 0.1, 8, 8),      # 1 -> 0 groups: still one
    (8, 0.5, 8, 4),       # no wider than one group: plain floor
    (6, 0.5, 8, 3),
    (1, 0.5, 8, 1),       # never 0: narrowing is not removing
    (3, 0.9, 8, 2),
    (48, 0.75, 16, 32),
])
def test_narrowed_widths_keep_whole_groups_of_channels(width, shrink, align, expected) -> None:
    assert _aligned(width, shrink, align) == expected


@pytest.mark.parametrize("kind, width, removable, expected", [
    (ATTN_BLOCK, 1, True, [0]),      # a block goes whole or stays
    (RES, 16, True, [8, 0]),         # narrowed, then removed
    (ATTN_FF, 32, False, [16]),      # narrowed only: a GEGLU keeps a channel
    (RES, 1, True, [0]),             # one channel cannot narrow: no cut that changes nothing
    (ATTN_FF, 1, False, []),
])
def test_the_widths_a_round_tries(kind, width, removable, expected) -> None:
    unit = Unit("u", kind, 0, None, width, removable, "/u/")
    assert candidate_widths(unit, shrink=0.5, align=8) == expected


def test_pose_distance_is_the_mean_joint_distance() -> None:
    a = {"pose": torch.zeros(2, 3, 16, 3)}
    b = {"pose": torch.zeros(2, 3, 16, 3)}
    b["pose"][..., 0] = 3.0
    b["pose"][..., 1] = 4.0   # 5 mm at every joint
    b["pose"][0, 0, 0] = torch.tensor([0.0, 0.0, 96.0 * 5 + 5.0])  # one joint 485 mm: +5 mm on the mean of 96
    expected = (95 * 5.0 + math.sqrt(485.0 ** 2)) / 96
    assert pose_distance_mm(a, b) == pytest.approx(expected)
    assert pose_distance_mm(b, a) == pytest.approx(expected)


@pytest.fixture(scope="module")
def candidates():
    """The randomised tiny, stages.0.block1's channels 4-7 silenced (conv2 reads nothing from
    them), its candidates at shrink 0.5 / align 8 over two causal windows."""
    model = randomised_tiny(11)
    with torch.no_grad():
        model.stages[0].block1.conv2.weight[:, 4:] = 0.0
    frames = (torch.rand(1, 2, 2, 64, 96, generator=torch.Generator().manual_seed(2)) < 0.1).float()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    # one unit profiled: 2 ms of kernels over 5 nodes, in a 10 ms step of which 6 ms are kernels
    # over 100 nodes (dispatch: 0.04 ms a node)
    profile = LatencyProfile(run_ms=10.0, kernel_ms=6.0, nodes=100, units={"stages.0.block1": UnitLatency(2.0, 5)})
    found = measure_candidates(model, frames, 20.0, shrink=0.5, align=8, profile=profile)
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # the model is left as it was
    return model, found


def test_every_unit_is_tried_narrowed_and_removable_ones_removed(candidates) -> None:
    """Widths per unit, in unit order: an attention block is only removed; every other unit is
    narrowed by the shrink (aligned) when that narrows it, and removed too when removable."""
    model, found = candidates
    expected = []
    for unit in prunable_units(model.config):
        if unit.kind == ATTN_BLOCK:
            expected.append((unit.name, 0, 1))
            continue
        if _aligned(unit.width, 0.5, 8) < unit.width:
            expected.append((unit.name, _aligned(unit.width, 0.5, 8), unit.width))
        if unit.removable:
            expected.append((unit.name, 0, unit.width))
    assert [(c.unit, c.width, c.old_width) for c in found] == expected
    assert any(c.width == 0 and c.old_width > 1 for c in found)  # a residual block removed
    saved = {(c.unit, c.width): c.saved_ms for c in found}
    assert saved.pop(("stages.0.block1", 4)) == pytest.approx(2.0 * (1 - 4 / 8))  # half its kernels
    assert saved.pop(("stages.0.block1", 0)) == pytest.approx(2.0 + 5 * 0.04)   # its kernels and dispatch
    assert set(saved.values()) == {0.0}  # the units the profile does not time save nothing measured


def test_a_cut_of_silenced_channels_does_no_damage(candidates) -> None:
    """stages.0.block1 narrowed to 4 keeps the four channels that contribute (the importance
    ranks the silenced ones last): the poses do not move; other cuts move them."""
    _, found = candidates
    by_cut = {(c.unit, c.width): c for c in found}
    assert by_cut[("stages.0.block1", 4)].damage_mm < 1e-3
    assert by_cut[("stages.0.block1", 0)].damage_mm > 1.0
    assert by_cut[("stages.1.block1", 8)].damage_mm > 1e-2 and by_cut[("attention.0.ff", 16)].damage_mm > 1e-2
    assert all(math.isfinite(c.damage_mm) and c.damage_mm >= 0 for c in found)


def test_mac_savings_follow_the_layers_each_cut_touches(candidates) -> None:
    """From the unpruned model's per-module counts: removing an attention block saves all of its
    layers' MACs; narrowing a residual block's hidden width from w to w' saves (w - w') / w of
    its two convolutions' (both are linear in that width)."""
    model, found = candidates
    per_module = count_macs(model)
    by_cut = {(c.unit, c.width): c for c in found}
    attention = sum(v for k, v in per_module.items() if k.startswith("attention.1."))
    assert attention > 0 and by_cut[("attention.1", 0)].saved_macs == attention
    block = [u for u in prunable_units(model.config) if u.kind == RES][0]
    convs = per_module[f"{block.name}.conv1"] + per_module[f"{block.name}.conv2"]
    assert by_cut[(block.name, 4)].saved_macs == convs * (block.width - 4) // block.width
    assert by_cut[(block.name, 0)].saved_macs == convs + 0  # the shortcut has no convolution in this block
    assert sum(per_module.values()) == total_macs(model)


def test_module_macs_against_the_layer_formulas() -> None:
    """A Conv2d: output values x in/groups x kernel area; a Linear: output values x in features;
    batch 1, one step: the stem's first convolution (2 -> 8 channels, 3 x 3, stride 2, on the
    64 x 96 frame) and the pose head (16 joints x 3 outputs from 40 features)."""
    model = randomised_tiny(3)
    macs = count_macs(model)
    stem = model.stem[0]
    assert (stem.in_channels, stem.out_channels, stem.kernel_size, stem.stride, stem.padding) == (2, 8, (3, 3), (2, 2), (1, 1))
    assert macs["stem.0"] == (8 * 32 * 48) * (2 * 3 * 3)
    assert (model.delta_head.in_features, model.delta_head.out_features) == (40, 3)
    assert macs["delta_head"] == (16 * 3) * 40
    assert not model.training and total_macs(model.train()) == sum(macs.values())
    assert model.training  # counting leaves the mode as it found it


# --- the greedy choice's ranking (module docstring: damage per unit of gain; the gain is the
# share of the step a cut saves, plus a thousandth of its share of the largest MAC saving)

UNITS = prunable_units(e3dpsm.create_model("tiny").config)


def _profile(run_ms: float) -> LatencyProfile:
    return LatencyProfile(run_ms=run_ms, kernel_ms=run_ms, nodes=10, units={})


def _first(candidates: list[Candidate], profile: LatencyProfile | None) -> str:
    """The first cut chosen (MACs objective, a target one MAC away: the first cut reaches it)."""
    widths, _ = choose(candidates, UNITS, "macs", current=10_000, target=9_999, profile=profile)
    assert len(widths) == 1
    return next(iter(widths))


def _cut(unit: str, saved_ms: float, saved_macs: int, damage: float = 1.0, width: int = 4) -> Candidate:
    return Candidate(unit, width, 8, damage_mm=damage, saved_macs=saved_macs, saved_ms=saved_ms)


def test_measured_time_outranks_counted_macs() -> None:
    """Equal damage: a cut saving a tenth of the step beats one saving ten times its MACs and no time."""
    timed, counted = _cut("stages.0.block1", 1.0, 100), _cut("stages.1.block1", 0.0, 1000)
    assert _first([counted, timed], _profile(10.0)) == "stages.0.block1"


@pytest.mark.parametrize("run_ms, saved_ms, first", [
    (10.0, 0.005, "stages.1.block1"),   # 5e-4 of the step < the MAC term's 1e-3: the MACs decide
    (10.0, 0.02, "stages.2.block1"),    # 2e-3 of the step: the time decides
    (0.5, 0.0008, "stages.2.block1"),   # 1.6e-3 of a 0.5 ms step
    (0.0, 0.0015, "stages.2.block1"),   # a profile without a run time: shares of 1 ms
    (0.0, 0.0005, "stages.1.block1"),
    (None, 0.0015, "stages.2.block1"),  # no profile: shares of 1 ms
    (None, 0.0005, "stages.1.block1"),
])
def test_macs_weigh_a_thousandth_of_the_step(run_ms, saved_ms, first) -> None:
    counted = _cut("stages.1.block1", 0.0, 1000)   # the largest MAC saving: MAC term 1e-3
    timed = _cut("stages.2.block1", saved_ms, 1)
    profile = None if run_ms is None else _profile(run_ms)
    assert _first([counted, timed], profile) == first


def test_a_cut_that_saves_nothing_counted_is_never_chosen() -> None:
    """MACs objective: a cut saving no MACs is left out (its gain could be 0: no division by it);
    latency objective: a cut saving no measured time is left out, however harmless."""
    free = _cut("stages.0.block1", 0.0, 0, damage=0.0)
    assert _first([free, _cut("stages.1.block1", 0.0, 5)], None) == "stages.1.block1"
    untimed = _cut("stages.0.block1", 0.0, 50, damage=0.0)
    profile = LatencyProfile(run_ms=10.0, kernel_ms=10.0, nodes=10, units={"stages.1.block1": UnitLatency(2.0, 2)})
    widths, _ = choose([untimed, _cut("stages.1.block1", 1.0, 5)], UNITS, "latency", current=10.0, target=9.5,
                       profile=profile)
    assert widths == {"stages.1.block1": 4}
    assert _first([untimed, _cut("stages.1.block1", 1.0, 5)], _profile(10.0)) == "stages.0.block1"


def test_a_units_second_cut_is_skipped_and_the_next_unit_taken() -> None:
    cands = [_cut("stages.0.block1", 1.0, 10, damage=1.0), _cut("stages.0.block1", 1.0, 10, damage=1.1, width=0),
             _cut("stages.1.block1", 1.0, 10, damage=5.0)]
    widths, value = choose(cands, UNITS, "macs", current=100, target=80, profile=None)
    assert widths == {"stages.0.block1": 4, "stages.1.block1": 4} and value == 80


def test_a_block_removed_beside_a_narrowed_unit_elsewhere() -> None:
    """Only units inside a removed block's scope stop its removal."""
    cands = [_cut("stages.0.block1", 1.0, 10, damage=0.1), Candidate("attention.1", 0, 1, 1.0, 10, 1.0)]
    widths, _ = choose(cands, UNITS, "macs", current=100, target=80, profile=None)
    assert widths == {"stages.0.block1": 4, "attention.1": 0}


def test_an_unknown_objective_is_named() -> None:
    with pytest.raises(ValueError, match="^unknown objective 'speed'$"):
        choose([], UNITS, "speed", current=1.0, target=0.5)


def test_macs_by_stage_put_the_stem_and_the_decoder_and_heads_apart() -> None:
    model = randomised_tiny(3)
    per_module = count_macs(model)
    groups = macs_per_stage(model)
    assert set(groups) == {"stem", "stage1", "stage2", "stage3", "stage4", "decoder+heads"}
    assert groups["stem"] == sum(v for k, v in per_module.items() if k.startswith("stem."))
    assert groups["decoder+heads"] == sum(v for k, v in per_module.items()
                                          if k.split(".")[0] not in ("stem", "stages", "attention", "ssm"))
    assert groups["decoder+heads"] >= per_module["delta_head"] > 0


def test_macs_are_whole_numbers_over_any_kernel_shape_and_grouping() -> None:
    """A 1 x 3 kernel in two groups (the stem swapped for one, same output size): output values x
    in/groups x kernel area, an integer."""
    model = randomised_tiny(3)
    model.stem[0] = torch.nn.Conv2d(2, 8, kernel_size=(1, 3), stride=2, padding=(0, 1), groups=2)
    macs = count_macs(model)
    assert macs["stem.0"] == (8 * 32 * 48) * (2 // 2 * 1 * 3)
    assert all(isinstance(v, int) for v in macs.values())


def test_candidates_are_values() -> None:
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError):
        _cut("stages.0.block1", 1.0, 1).width = 2


def test_a_largest_saving_of_one_mac_weighs_a_full_thousandth() -> None:
    """The MAC term is the share of the largest MAC saving, even when that is 1 MAC: a cut of 1
    MAC and no time (gain 1e-3) against one of 1 MAC and 7e-4 of a 1 ms step (gain 1.7e-3), at
    1.0 and 1.8 mm: 1,000 against 1,059 mm per unit of gain, so the first."""
    untimed = _cut("stages.1.block1", 0.0, 1, damage=1.0)
    timed = _cut("stages.2.block1", 0.0007, 1, damage=1.8)
    assert _first([timed, untimed], _profile(1.0)) == "stages.1.block1"
