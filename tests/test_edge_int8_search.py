"""The INT8 `.pte`'s return-to-float search (export/executorch_int8.py): its units are the
blocks of the quantised scopes, a kept-float block is left out of the quantizer's annotation
by whole module paths, and its trials run the converted PT2E module in PyTorch with states
carried: with every block kept float that is the float step, with none it is not.

The search's outcome on a real program (the trained tiny within budget once it keeps a
block float) is the slow `test_edge_int8.py::test_int8_program_is_within_budget`."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from _edge_helpers import Judged, skip_without
from e3dpsm.errors import ConfigError

TINY_GROUPS = ["model.stem", "model.stages.0", "model.stages.1", "model.stages.2", "model.stages.3",
               "model.attention.0", "model.attention.1", "model.attention.2", "model.attention.3",
               "model.ssm", "model.decoder"]


def test_search_units_are_the_quantised_blocks(edge_model) -> None:
    skip_without("executorch")
    from e3dpsm.export.executorch_int8 import search_groups

    groups = search_groups(edge_model)
    assert [name for name, _ in groups] == TINY_GROUPS
    assert all(paths == [name] for name, paths in groups)


def test_a_block_of_only_recurrent_layers_is_no_search_unit() -> None:
    skip_without("executorch")
    from e3dpsm.export.executorch_int8 import _quantisable_layers
    from e3dpsm.layers.s5 import S5

    s5 = next(m for m in __import__("e3dpsm").create_model("tiny").modules() if isinstance(m, S5))
    assert _quantisable_layers(torch.nn.ModuleList([s5])) == 0
    assert _quantisable_layers(torch.nn.ModuleList([s5, torch.nn.Linear(2, 2)])) == 1


def _node_at(path: str) -> torch.fx.Node:
    graph = torch.fx.Graph()
    node = graph.call_function(torch.relu, (graph.placeholder("x"),))
    node.meta["nn_module_stack"] = {"outer": ("model", object), "inner": (path, object)}
    return node


@pytest.mark.parametrize("path, keep_float, quantised", [
    ("model.stages.1.block1.conv", (), True),
    ("model.stages.1.block1.conv", ("model.stages.1",), False),
    ("model.stages.1", ("model.stages.1",), False),
    ("model.stages.10.conv", ("model.stages.1",), True),  # a path prefix, not a string prefix
    ("model.stages.0.conv", ("model.stages.1", "model.stem"), True),
    ("model.direct_head", (), False),  # outside the quantised scopes whatever the search says
])
def test_keep_float_takes_whole_module_paths(path, keep_float, quantised) -> None:
    skip_without("executorch")
    from e3dpsm.export.executorch_int8 import in_quantised_scope

    assert in_quantised_scope(_node_at(path), keep_float) is quantised


def test_the_search_needs_a_split_of_its_own() -> None:
    from e3dpsm.export.edge_int8 import EdgeInt8Options

    with pytest.raises(ConfigError, match="search split .'test'. must differ"):
        EdgeInt8Options(search_split="test")
    with pytest.raises(ConfigError, match="search split .'train'. must differ"):
        EdgeInt8Options(search_split="train")
    EdgeInt8Options(search_split="test", search_rounds=0)  # no search: no split of its own needed
    with pytest.raises(ConfigError, match="--search-rounds must be 0 or positive"):
        EdgeInt8Options(search_rounds=-1)


@pytest.fixture(scope="module")
def trial_steppers(edge_model, quant_data):
    """The trained tiny's step converted twice by PT2E on 4 calibration frames: every search
    unit kept float, and none."""
    skip_without("executorch")
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export.edge_export import export_ready
    from e3dpsm.export.executorch_export import ExecuTorchOptions, quantized_module, step_program
    from e3dpsm.export.executorch_int8 import (QuantizedModuleStepper, calibrator, search_groups,
                                               xnnpack_int8_quantizer)

    frames = np.asarray(PreparedData.open(quant_data).split("train")[0].lnes[:4], dtype=np.float32)
    state = {k: v for k, v in edge_model.init_state(1).items()}
    names = [s.name for s in edge_model.state_spec()]
    inputs = [(torch.from_numpy(f[None]), torch.full((1,), 20.0), *(state[n] for n in names)) for f in frames]
    every_block = [name for name, _ in search_groups(edge_model)]
    with export_ready(edge_model, ExecuTorchOptions().attention_form):
        program = step_program(edge_model, ExecuTorchOptions())
        steppers = {kept: QuantizedModuleStepper(quantized_module(program, xnnpack_int8_quantizer(blocks),
                                                                  calibrator(inputs)), edge_model)
                    for kept, blocks in (("all", every_block), ("none", ()))}
    return steppers


def _rollout(stepper, frames: np.ndarray) -> tuple[np.ndarray, dict]:
    state, poses = stepper.init_state(1), []
    for frame in frames:
        out, state = stepper.step(np.ascontiguousarray(frame[None]), state, 20.0)
        poses.append(out["pose"][0])
    return np.stack(poses), state


def test_a_trial_with_every_block_float_is_the_float_step(trial_steppers, edge_model, quant_data) -> None:
    """States carried through the converted module's positional outputs: a swapped pair, or a
    block the keep-float list missed, would move the poses far past 1e-3 mm."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export.torch_stepper import TorchStepper

    frames = np.asarray(PreparedData.open(quant_data).split("val")[0].lnes[:12], dtype=np.float32)
    got, got_state = _rollout(trial_steppers["all"], frames)
    want, want_state = _rollout(TorchStepper(edge_model), frames)
    np.testing.assert_allclose(got, want, atol=1e-3)
    for name, value in want_state.items():
        np.testing.assert_allclose(got_state[name], value, atol=1e-4, err_msg=name)
    eight_bit, _ = _rollout(trial_steppers["none"], frames)
    assert np.abs(eight_bit - want).max() > 0.1  # the same frames through 8 bits do move


def test_narrowing_returns_a_kept_blocks_operators_to_8_bits_one_at_a_time(monkeypatch) -> None:
    """A kept block of three units of which only `b` needs float: the narrowing tries each unit
    in 8 bits in the order given, keeps the two that hold the budget there and leaves `b`
    float; a kept block of one unit is not narrowed (its unit is the block), and the trials
    record every try with its verdict."""
    from e3dpsm.export import edge_int8

    tried = []

    def judged(floats, _search, _budget):
        tried.append(tuple(floats))
        return Judged("blk/b" in floats, 0.5 if "blk/b" in floats else 2.0)

    monkeypatch.setattr(edge_int8, "check_stepper", judged)
    units = {"blk": ["blk/a", "blk/b", "blk/c"], "one": ["one/x"]}
    narrowing = edge_int8.narrow_float_groups(["blk", "one", "whole"], units, lambda floats: floats, None,
                                              edge_int8.EdgeInt8Options(), "fake")
    assert narrowing.floats == ["blk/b", "one", "whole"] and narrowing.untried == []
    assert tried == [("blk/b", "blk/c", "one", "whole"), ("blk/c", "one", "whole"), ("blk/b", "one", "whole")]
    assert [(t["unit"], t["within"]) for t in narrowing.trials] == [("blk/a", True), ("blk/b", False),
                                                                    ("blk/c", True)]
    assert all(t["group"] == "blk" for t in narrowing.trials)


@pytest.mark.parametrize("cap, tried_units, floats", [
    (0, [], ["blk/a", "blk/b", "blk/c", "two/x", "two/y"]),
    (2, ["blk/a", "blk/b"], ["blk/b", "blk/c", "two/x", "two/y"]),
    (4, ["blk/a", "blk/b", "blk/c", "two/x"], ["blk/b", "two/y"]),
    (5, ["blk/a", "blk/b", "blk/c", "two/x", "two/y"], ["blk/b"]),
    (9, ["blk/a", "blk/b", "blk/c", "two/x", "two/y"], ["blk/b"]),
])
def test_narrowing_stops_after_its_trial_cap_and_leaves_the_rest_float(monkeypatch, cap, tried_units,
                                                                       floats) -> None:
    """--narrow-trials N: the first N units in order (block by block, largest first within
    each) are tried; the units past the cap stay float and are named as untried."""
    from e3dpsm.export import edge_int8

    monkeypatch.setattr(edge_int8, "check_stepper", lambda floats, _s, _b: Judged("blk/b" in floats, 0.5))
    units = {"blk": ["blk/a", "blk/b", "blk/c"], "two": ["two/x", "two/y"]}
    narrowing = edge_int8.narrow_float_groups(["blk", "two"], units, lambda floats: floats, None,
                                              edge_int8.EdgeInt8Options(narrow_trials=cap), "fake")
    assert [t["unit"] for t in narrowing.trials] == tried_units
    assert narrowing.floats == floats
    assert narrowing.untried == [u for u in ["blk/a", "blk/b", "blk/c", "two/x", "two/y"] if u not in tried_units]


def test_a_negative_narrowing_cap_is_refused() -> None:
    with pytest.raises(ConfigError, match="--narrow-trials must be 0 or positive, got -1"):
        __import__("e3dpsm.export.edge_int8", fromlist=["x"]).EdgeInt8Options(narrow_trials=-1)


def test_a_pte_blocks_units_are_its_8_bit_layers_largest_first(edge_model) -> None:
    """The `.pte` narrowing's units: every convolution and linear layer of the block that would
    take 8 bits (none of an S5 layer's), largest weights first; given the traced program, only
    the layers its graph calls (the attention export folds some projections into others)."""
    skip_without("executorch")
    from e3dpsm.export.edge_export import export_ready
    from e3dpsm.export.executorch_export import ExecuTorchOptions, step_program
    from e3dpsm.export.delegation import module_scope
    from e3dpsm.export.executorch_int8 import operator_units

    units = operator_units(edge_model, "model.attention.3")
    layers = [edge_model.get_submodule(u.removeprefix("model.")) for u in units]
    assert layers and all(isinstance(m, (torch.nn.Conv2d, torch.nn.Linear)) for m in layers)
    sizes = [m.weight.numel() for m in layers]
    assert sizes == sorted(sizes, reverse=True)
    block = edge_model.get_submodule("attention.3")
    assert len(units) == sum(isinstance(m, (torch.nn.Conv2d, torch.nn.Linear)) for m in block.modules())
    with export_ready(edge_model, ExecuTorchOptions().attention_form):
        program = step_program(edge_model, ExecuTorchOptions())
        called = operator_units(edge_model, "model.attention.3", program)
    scopes = {module_scope(n) for n in program.graph_module.graph.nodes if n.op == "call_function"}
    assert called and set(called) < set(units) and all(u in scopes for u in called)
    assert [u for u in units if u in called] == called  # the order kept
    ssm = operator_units(edge_model, "model.ssm")
    assert ssm and not any(".s5" in u or "Projection" in u for u in ssm)
