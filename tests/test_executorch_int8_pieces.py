"""The INT8 `.pte` converter's own pieces (export/executorch_int8.py), each in seconds: the
quantizer's annotation on a toy shaped like the step wrapper (conv / linear inside the
quantised scopes, the recurrent types, the search's keep-float paths and everything outside
left float), the feeds mapped onto the traced step, the PT2E stepper's state plumbing, what
`convert.json` counts as running in 8 bits, and convert_executorch_int8's order of work with
its long parts recorded. The real conversion of the trained tiny is the slow
test_edge_int8.py; the search's units on the tiny are test_edge_int8_search.py."""
from __future__ import annotations

import types

import numpy as np
import pytest
import torch
from torch import nn

pytest.importorskip("executorch", reason="executorch (pip extra executorch) is not installed")

from _model_helpers import converter_tiny  # noqa: E402
from _toy_pt2e import ToyRecurrent, toy_program as exported_toy  # noqa: E402
from e3dpsm.export import delegation, edge_export, executorch_export, executorch_int8  # noqa: E402
from e3dpsm.export.executorch_int8 import (QuantizedModuleStepper, calibrator, in_quantised_scope,  # noqa: E402
                                           int8_coverage, keep_float_record, mac_nodes, step_inputs,
                                           xnnpack_int8_quantizer)
from e3dpsm.models import OUTPUT_NAMES  # noqa: E402


@pytest.fixture(scope="module")
def toy_program():
    return exported_toy()


def _converted(toy_program, monkeypatch, keep_float=()) -> torch.fx.GraphModule:
    program, example = toy_program
    monkeypatch.setattr(executorch_int8, "KEEP_FLOAT_TYPES", (ToyRecurrent,))
    return executorch_export.quantized_module(program, xnnpack_int8_quantizer(keep_float),
                                              calibrator([example, (2 * example[0],)]))


def _weights_in_8_bits(module: torch.fx.GraphModule) -> dict[str, bool]:
    """Module path of every conv / linear -> whether its weight went through 8 bits."""
    return {delegation.module_scope(n): "dequantize_per_channel" in executorch_int8.op_name(n.args[1])
            for n in module.graph.nodes if n.op == "call_function"
            and str(n.target) in ("aten.conv2d.default", "aten.linear.default")}


def test_conv_and_linear_inside_the_scopes_take_8_bits_and_nothing_else(toy_program, monkeypatch) -> None:
    weights = _weights_in_8_bits(_converted(toy_program, monkeypatch))
    assert weights == {"model.stem": True, "model.stages.0": True, "model.stages.1": True, "model.ssm.proj": True,
                       "model.ssm.rec.lin": False,  # the recurrent type, inside a quantised scope
                       "model.decoder": True, "model.direct_head": False}  # outside every scope


def test_the_search_keeps_whole_module_paths_float(toy_program, monkeypatch) -> None:
    weights = _weights_in_8_bits(_converted(toy_program, monkeypatch, ("model.stages.0", "model.ssm")))
    assert [path for path, eight in weights.items() if eight] == ["model.stem", "model.stages.1", "model.decoder"]


def test_element_wise_ops_and_concatenations_stay_float_with_their_scalars(toy_program, monkeypatch) -> None:
    """Only QUANTISED_OPERATORS are annotated: no quantize after the scalar product, the sum or
    the concatenation (XNNPACK's global config annotates `cat` past the filter), and the
    scalars stay Python numbers (XNNPACK's own transform makes them float tensors, which broke
    the gather form's index arithmetic)."""
    module = _converted(toy_program, monkeypatch)
    nodes = {str(n.target): n for n in module.graph.nodes if n.op == "call_function"}
    for target in ("aten.add.Tensor", "aten.cat.default"):
        assert not [u for u in nodes[target].users if "quantize_per_tensor" in str(u.target)], target
    assert [type(a) for a in nodes["aten.mul.Tensor"].args] == [torch.fx.Node, float]
    assert [type(a) for a in nodes["aten.add.Tensor"].args] == [torch.fx.Node, float]
    assert not [n for n in module.graph.nodes if n.op == "get_attr" and "_tensor_constant" in n.target]


def test_each_conversion_calibrates_its_own_prepared_module(toy_program, monkeypatch) -> None:
    """quantized_module prepares a fresh copy each call (trials must not share observers) and
    hands calibrate the prepared module, observers and all."""
    program, example = toy_program
    monkeypatch.setattr(executorch_int8, "KEEP_FLOAT_TYPES", (ToyRecurrent,))
    seen = []

    def calibrate(prepared):
        seen.append(prepared)
        prepared(*example)

    first = executorch_export.quantized_module(program, xnnpack_int8_quantizer(), calibrate)
    second = executorch_export.quantized_module(program, xnnpack_int8_quantizer(("model.stem",)), calibrate)
    assert len(seen) == 2 and seen[0] is not seen[1]
    assert any("observer" in type(m).__name__.lower() for m in seen[0].modules())
    assert _weights_in_8_bits(first)["model.stem"] and not _weights_in_8_bits(second)["model.stem"]
    with torch.no_grad():
        want = program.module()(*example)[0]
        assert (first(*example)[0] - want).abs().max() > 0  # rounded
        torch.testing.assert_close(first(*example)[0], want, atol=0.05, rtol=0.05)


def test_a_get_attr_follows_its_reader() -> None:
    graph = torch.fx.Graph()
    weight = graph.get_attr("model_direct_head_weight")  # carries no module path
    assert in_quantised_scope(weight, ("model.stem",)) is True
    bare = graph.call_function(torch.relu, (weight,))
    assert delegation.module_scope(bare) == "" and in_quantised_scope(bare) is False


def test_the_keep_float_record_names_what_stays_float() -> None:
    assert keep_float_record() == {
        "quantised_scopes": ["model.stem", "model.stages", "model.attention", "model.ssm", "model.decoder"],
        "module_types": ["S5", "PoseFusion"],
        "float_elsewhere": ["direct_head", "delta_head", "pose_embed", "fusion", "pose prior and unit scaling"]}


def test_step_inputs_follow_the_spec_order_as_contiguous_float32() -> None:
    feeds = [{"b": np.arange(6, dtype=np.float64).reshape(2, 3).T, "a": np.ones(2, np.float16), "extra": 1},
             {"a": np.zeros(2), "b": np.zeros((3, 2))}]
    inputs = step_inputs(types.SimpleNamespace(feeds=feeds), ["a", "b"])
    assert len(inputs) == 2 and all(len(args) == 2 for args in inputs)
    a, b = inputs[0]
    assert a.dtype == b.dtype == torch.float32 and b.is_contiguous()
    np.testing.assert_array_equal(b.numpy(), feeds[0]["b"])
    np.testing.assert_array_equal(a.numpy(), np.ones(2))
    with pytest.raises(ValueError, match=r"^calibration feeds lack \['c'\]: recorded from another model's graph$"):
        step_inputs(types.SimpleNamespace(feeds=feeds), ["a", "c"])


def test_the_calibrator_runs_every_recorded_step_without_gradients() -> None:
    calls = []

    def prepared(*args):
        calls.append((args, torch.is_grad_enabled()))

    inputs = [(torch.ones(1),), (torch.zeros(1), torch.ones(2))]
    calibrator(inputs)(prepared)
    assert [args for args, _ in calls] == inputs and [grad for _, grad in calls] == [False, False]


@pytest.fixture(scope="module")
def tiny():
    return converter_tiny()


def test_the_pt2e_stepper_hands_states_in_the_specs_order_and_splits_its_outputs(tiny) -> None:
    names = [s.name for s in tiny.state_spec()]
    calls = []

    def module(lnes, window, *states):
        assert not torch.is_grad_enabled()  # a search steps thousands of frames: no graph kept
        calls.append((lnes, window, states))
        poses = tuple(torch.full((1, 2), float(i)) for i in range(len(OUTPUT_NAMES)))
        return poses + tuple(s + window[0] for s in states)

    stepper = QuantizedModuleStepper(module, tiny)
    state = stepper.init_state()
    assert list(state) == names and all(isinstance(v, np.ndarray) and v.shape[0] == 1 for v in state.values())
    assert all(v.shape[0] == 3 for v in stepper.init_state(3).values())
    state = {n: np.full_like(v, k) for k, (n, v) in enumerate(state.items())}
    lnes = np.ones((1, 2, 32, 64), np.float32)
    poses, new_state = stepper.step(lnes, state, 20.0)
    (got_lnes, window, states), = calls
    np.testing.assert_array_equal(got_lnes.numpy(), lnes)
    assert window.tolist() == [20.0]
    assert [float(s.flatten()[0]) for s in states] == list(range(len(names)))
    assert list(poses) == list(OUTPUT_NAMES) and [float(p[0, 0]) for p in poses.values()] == list(
        range(len(OUTPUT_NAMES)))
    assert list(new_state) == names
    assert [float(v.flatten()[0]) for v in new_state.values()] == [k + 20.0 for k in range(len(names))]


def test_a_trial_converts_with_its_floats_and_steps_the_result(tiny, monkeypatch) -> None:
    made = []
    monkeypatch.setattr(executorch_int8, "quantized_module",
                        lambda program, quantizer, calibrate: made.append((program, quantizer, calibrate)) or "MOD")
    monkeypatch.setattr(executorch_int8, "xnnpack_int8_quantizer", lambda floats: ("Q", tuple(floats)))
    calibrate = object()
    stepper = executorch_int8._trial(tiny, "PROGRAM", calibrate)(["model.stem"])
    assert made == [("PROGRAM", ("Q", ("model.stem",)), calibrate)]
    assert isinstance(stepper, QuantizedModuleStepper) and stepper.module == "MOD" and stepper.model is tiny


def test_the_search_runs_over_the_tinys_blocks(tiny, monkeypatch) -> None:
    seen = {}

    def search(groups, trial, search_set, options, runtime):
        seen.update(groups=groups, trial=trial, search=search_set, options=options, runtime=runtime)
        return "PLACEMENT"

    monkeypatch.setattr(executorch_int8, "search_float_groups", search)
    options = executorch_int8.EdgeInt8Options()
    assert executorch_int8.search_keep_float(tiny, "PROGRAM", "CAL", "SEARCH", options) == "PLACEMENT"
    assert seen["groups"] == [name for name, _ in executorch_int8.search_groups(tiny)] and len(seen["groups"]) == 11
    assert (seen["search"], seen["options"], seen["runtime"]) == ("SEARCH", options, "PyTorch (PT2E)")
    assert callable(seen["trial"])


# What convert.json counts as run in 8 bits: a MAC operator whose input and weight both
# arrive dequantized. A float operator reading a quantised neighbour's output (the matmul of a
# decomposed LayerNorm, a kept-float convolution after an 8-bit one) reads a dequantized
# activation but runs in float.
def _mac_graph() -> torch.fx.Graph:
    import torchao.quantization.pt2e.quantize_pt2e  # noqa: F401  (registers the quantized_decomposed ops)

    graph = torch.fx.Graph()
    x = graph.placeholder("x")

    def tensor(node: torch.fx.Node, shape: tuple[int, ...]) -> torch.fx.Node:
        node.meta["val"] = torch.empty(shape)
        return node

    def dq(node: torch.fx.Node, shape: tuple[int, ...], name: str = "dequantize_per_tensor") -> torch.fx.Node:
        return tensor(graph.call_function(getattr(torch.ops.quantized_decomposed, name).default,
                                          (node, 0.1, 0, -128, 127, torch.int8)), shape)

    def scoped(node: torch.fx.Node, path: str) -> torch.fx.Node:
        node.meta["nn_module_stack"] = {"a": ("model", object), "b": (path, object)}
        return node

    tensor(x, (1, 4, 8, 8))
    act = dq(x, (1, 4, 8, 8))
    w8 = dq(tensor(graph.placeholder("w8"), (4, 4, 1, 1)), (4, 4, 1, 1))
    wf = tensor(graph.placeholder("wf"), (4, 4, 1, 1))
    conv = torch.ops.aten.convolution.default
    both = scoped(tensor(graph.call_function(conv, (act, w8, None, [1, 1], [0, 0], [1, 1], False, [0, 0], 1)),
                         (1, 4, 8, 8)), "model.stem")
    scoped(tensor(graph.call_function(conv, (act, wf, None, [1, 1], [0, 0], [1, 1], False, [0, 0], 1)),
                  (1, 4, 8, 8)), "model.stages.0")
    rows = tensor(graph.placeholder("rows"), (8, 4))
    scoped(tensor(graph.call_function(torch.ops.aten.mm.default, (dq(rows, (8, 4)), tensor(graph.placeholder("m"),
                                                                                            (4, 4)))), (8, 4)),
           "model.attention.0.norm")
    scoped(tensor(graph.call_function(torch.ops.aten.relu.default, (both,)), (1, 4, 8, 8)), "model.stem")
    one = tensor(graph.placeholder("one"), (1, 1))  # a product of one multiply-accumulate still counts
    scoped(tensor(graph.call_function(torch.ops.aten.mm.default, (one, one)), (1, 1)), "model.decoder")
    return graph


def test_mac_nodes_count_8_bits_where_input_and_weight_are_dequantized() -> None:
    assert mac_nodes(_mac_graph()) == [("aten.convolution.default", "model.stem", True),
                                       ("aten.convolution.default", "model.stages.0", False),
                                       ("aten.mm.default", "model.attention.0.norm", False),
                                       ("aten.mm.default", "model.decoder", False)]


def test_coverage_splits_delegated_from_portable_by_operator() -> None:
    delegated = types.SimpleNamespace(original_module=types.SimpleNamespace(graph=_mac_graph()))
    other = _mac_graph()  # a second partition: its operators count too
    other.erase_node(next(n for n in other.nodes if str(n.target) == "aten.relu.default"))
    top = _mac_graph()  # its MAC nodes run on portable kernels, 8-bit or not
    call = top.call_function(torch.ops.higher_order.executorch_call_delegate, ())
    call.meta["val"] = torch.empty(2, 2)
    partitions = [delegated, nn.Identity(), types.SimpleNamespace(original_module=types.SimpleNamespace(graph=other))]
    program = types.SimpleNamespace(graph_module=types.SimpleNamespace(children=lambda: partitions),
                                    graph=top)
    coverage = int8_coverage(types.SimpleNamespace(exported_program=lambda: program))
    assert coverage == {
        "xnnpack_int8": {"aten.convolution.default": 2},
        "xnnpack_float": {"aten.convolution.default": 2, "aten.mm.default": 4},
        "portable": {"aten.convolution.default": 2, "aten.mm.default": 2},
        "float_modules": ["model.attention.0.norm", "model.decoder", "model.stages.0"],
        "int8_modules": ["model.stem"]}


class _Calibration(types.SimpleNamespace):
    def __len__(self) -> int:
        return 7


class Recorder:
    """convert_executorch_int8's long parts, recorded in the order they are called."""

    def __init__(self, monkeypatch, float_nodes: tuple[str, ...], narrowed: list[str]) -> None:
        self.calls: list[tuple] = []
        self.ready = False
        log = self.calls.append
        calibration = _Calibration(feeds=[{"x": np.zeros(1)}], state_source="fp32 rollout", seconds=1.234)
        placement = types.SimpleNamespace(float_nodes=float_nodes)

        def context(model, form):
            log(("export_ready", form))
            return _Ready(self)

        narrowing = types.SimpleNamespace(floats=narrowed,
                                          search_fields=lambda blocks: {"kept_float": list(narrowed),
                                                                        "blocks_kept_float": list(blocks)})
        patches = {
            (executorch_int8, "fp32_reference"): lambda model, work: log(("fp32_reference", work)) or "REF",
            (executorch_int8, "calibration_set"): lambda ref, data, options: log(("calibration", ref)) or calibration,
            (executorch_int8, "step_inputs"): lambda cal, names: log(("step_inputs", names)) or ["INPUTS"],
            (executorch_int8, "calibrator"): lambda inputs: log(("calibrator", inputs)) or "CALIBRATE",
            (executorch_int8, "search_set"): lambda ref, data, options: log(("search_set", ref)) or "SEARCH",
            (executorch_int8, "search_keep_float"):
                lambda model, traced, cal, search, options: log(("search", traced, cal, search, self.ready))
                or placement,
            (executorch_int8, "search_record"): lambda placement, search, options, runtime: {"runtime": runtime},
            (executorch_int8, "operator_units"):
                lambda model, group, traced: log(("units", group, traced)) or [group + ".a", group + ".b"],
            (executorch_int8, "narrow_float_groups"):
                lambda kept, units, trial, search, options, runtime: log(("narrow", tuple(kept), units, search,
                                                                          runtime, callable(trial))) or narrowing,
            (executorch_int8, "xnnpack_int8_quantizer"): lambda floats: ("QUANTIZER", tuple(floats)),
            (executorch_int8, "held_out_set"): lambda ref, data, options: log(("held_out", ref)) or "HELD",
            (executorch_int8, "check_artifact"): lambda path, runtime, held, options: log(("check", path, runtime,
                                                                                          held)) or "CHECK",
            (edge_export, "export_ready"): context,
            (edge_export, "step_spec"): lambda model: types.SimpleNamespace(input_names=["x"]),
            (executorch_export, "step_program"): lambda model, program: log(("trace", program.attention_form,
                                                                              self.ready)) or "TRACED",
            (executorch_export, "convert_executorch"):
                lambda model, path, program, precision, quantizer, calibrate, extra_record:
                log(("convert", path, program, precision, quantizer, calibrate, self.ready)) or
                types.SimpleNamespace(record=extra_record),
        }
        for (module, name), value in patches.items():
            monkeypatch.setattr(module, name, value)


class _Ready:
    def __init__(self, recorder: Recorder) -> None:
        self.recorder = recorder

    def __enter__(self) -> None:
        self.recorder.ready = True

    def __exit__(self, *exc) -> None:
        self.recorder.ready = False


@pytest.mark.parametrize("rounds, narrow, float_nodes, narrowed", [
    (0, None, (), []),
    (1, None, (), []),
    (4, None, (), []),
    (4, None, ("model.stem", "model.decoder"), ["model.stem.b", "model.decoder"]),
    (4, 0, ("model.stem",), ["unused"]),
])
def test_convert_judges_the_program_it_writes_with_the_search_it_ran(tiny, tmp_path, monkeypatch, rounds, narrow,
                                                                     float_nodes, narrowed) -> None:
    recorder = Recorder(monkeypatch, float_nodes, narrowed)
    options = executorch_int8.EdgeInt8Options(search_rounds=rounds, narrow_trials=narrow)
    program = executorch_export.ExecuTorchOptions(attention_form="gather")
    path = tmp_path / "step.pte"
    result, check, held = executorch_int8.convert_executorch_int8(tiny, "DATA", path, options, tmp_path, program)
    assert (check, held) == ("CHECK", "HELD")
    searched = rounds > 0
    narrowing = searched and bool(float_nodes) and narrow != 0
    keep = tuple(narrowed) if narrowing else float_nodes if searched else ()
    calls = recorder.calls
    expected = [("fp32_reference", tmp_path), ("calibration", "REF"), ("step_inputs", ["x"]),
                ("calibrator", ["INPUTS"])]
    if searched:
        expected += [("search_set", "REF"), ("export_ready", "gather"), ("trace", "gather", True),
                     ("search", "TRACED", "CALIBRATE", "SEARCH", True)]
    if narrowing:
        units = {g: [g + ".a", g + ".b"] for g in float_nodes}
        expected += [("units", g, "TRACED") for g in float_nodes]
        expected += [("narrow", float_nodes, units, "SEARCH", "PyTorch (PT2E)", True)]
    expected += [("convert", path, program, "int8", ("QUANTIZER", keep), "CALIBRATE", False), ("held_out", "REF"),
                 ("check", path, "executorch", "HELD")]
    assert calls == expected
    record = result.record
    assert record["calibration"] == {"split": "train", "frames": 7, "state_source": "fp32 rollout", "seconds": 1.23}
    assert record["budget"] == options.budget.to_dict()
    assert {k: v for k, v in record["keep_float"].items() if k != "searched"} == keep_float_record()
    if searched:
        assert record["keep_float"]["searched"] == list(keep)
        assert record["search"]["runtime"] == "PyTorch (PT2E)"
        assert ("blocks_kept_float" in record["search"]) is narrowing
        if narrowing:
            assert record["search"]["blocks_kept_float"] == list(float_nodes)
    else:
        assert list(record) == ["keep_float", "calibration", "budget"] and "searched" not in record["keep_float"]


def test_the_default_program_is_the_fp32_converters(tiny, tmp_path, monkeypatch) -> None:
    recorder = Recorder(monkeypatch, (), [])
    executorch_int8.convert_executorch_int8(tiny, "DATA", tmp_path / "s.pte",
                                            executorch_int8.EdgeInt8Options(search_rounds=0), tmp_path)
    convert = next(c for c in recorder.calls if c[0] == "convert")
    assert convert[2] == executorch_export.ExecuTorchOptions()


def test_the_search_units_of_the_tiny_are_its_blocks_holding_8_bit_layers(tiny) -> None:
    assert executorch_int8.search_groups(tiny) == [(name, [name]) for name in (
        "model.stem", "model.stages.0", "model.stages.1", "model.stages.2", "model.stages.3", "model.attention.0",
        "model.attention.1", "model.attention.2", "model.attention.3", "model.ssm", "model.decoder")]


def test_a_blocks_units_are_its_8_bit_layers_largest_first_and_those_the_program_calls(tiny) -> None:
    units = executorch_int8.operator_units(tiny, "model.ssm")
    layers = {path: tiny.get_submodule(path.removeprefix("model.")) for path in units}
    assert layers and all(type(m) in (nn.Conv2d, nn.Linear) for m in layers.values())
    assert not [p for p in units if ".s5." in p]  # the recurrent type's own layers stay float
    every = [f"model.ssm.{n}" for n, m in tiny.ssm.named_modules() if type(m) in (nn.Conv2d, nn.Linear)
             and ".s5" not in f".{n}"]
    assert sorted(units) == sorted(every)
    sizes = [m.weight.numel() for m in layers.values()]
    assert sizes == sorted(sizes, reverse=True) and sizes[0] > sizes[-1]
    graph = torch.fx.Graph()
    for path in (units[-1], units[0], "model.stem"):
        node = graph.call_function(torch.relu, (graph.placeholder(f"x{len(graph.nodes)}"),))
        node.meta["nn_module_stack"] = {"k": (path, object)}
    program = types.SimpleNamespace(graph_module=types.SimpleNamespace(graph=graph))
    assert executorch_int8.operator_units(tiny, "model.ssm", program) == [units[0], units[-1]]


@pytest.mark.parametrize("fold", [True, False])
def test_a_quantised_program_is_exported_again_and_folded_around_its_8_bit_weights(toy_program, monkeypatch,
                                                                                  fold) -> None:
    """export_step_program with a quantizer: the converted module exported again, calibrated
    once, its weights 8-bit constants each behind a dequantize, folded or not (folded with
    the fp32 program's skip list, an 8-bit weight and its dequantize become one float weight)."""
    program, example = toy_program
    monkeypatch.setattr(executorch_int8, "KEEP_FLOAT_TYPES", (ToyRecurrent,))
    monkeypatch.setattr(executorch_export, "step_program", lambda model, options: program)
    monkeypatch.setattr(executorch_export, "StepGraph", lambda model: types.SimpleNamespace(
        example_inputs=lambda batch: (example[0].expand(batch, *example[0].shape[1:]).contiguous(),)))
    calibrated = []
    result = executorch_export.export_step_program(
        "MODEL", executorch_export.ExecuTorchOptions(fold_constants=fold), xnnpack_int8_quantizer(),
        lambda prepared: calibrated.append(prepared(*example)))
    assert len(calibrated) == 1 and isinstance(result, torch.export.ExportedProgram)
    frame, = [n for n in result.graph.nodes if n.op == "placeholder" and n.name == "x"]
    assert tuple(frame.meta["val"].shape) == (1, 1, 8, 8)  # exported at batch 1, the step's
    targets = [str(n.target) for n in result.graph.nodes if n.op == "call_function"]
    assert targets.count("quantized_decomposed.dequantize_per_channel.default") == 5  # one per 8-bit weight
    int8_constants = [v for v in {**result.constants, **result.state_dict}.values()
                      if isinstance(v, torch.Tensor) and v.dtype == torch.int8]
    assert len(int8_constants) == 5  # PT2E's conversion quantised them; folding must not undo it
    assert "quantized_decomposed.quantize_per_channel.default" not in targets
    with torch.no_grad():
        torch.testing.assert_close(result.module()(*example)[0], program.module()(*example)[0], atol=0.05, rtol=0.05)
