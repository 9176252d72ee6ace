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

from _edge_helpers import skip_without
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
