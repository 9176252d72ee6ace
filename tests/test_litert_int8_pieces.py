"""The INT8 `.tflite` converter's own pieces (export/litert_int8.py), each in seconds on the toy
flatbuffer of tests/_toy_litert_int8.py: where each multiply-accumulate operator falls (a
group, a keep-float rule, neither, or two groups at once), the 8 bits placed by group and
kept float by rule, the calibration ranges against the toy's own activations computed in
PyTorch, the narrowing's units, and convert_litert_int8's order of work with the search's
parts recorded. The tiny's real flatbuffer is test_litert_int8.py's (slow fixture)."""
from __future__ import annotations

import copy
import re
import time
import types

import numpy as np
import pytest
import torch

pytest.importorskip("ai_edge_quantizer", reason="ai-edge-quantizer (pip extra litert) is not installed")
pytest.importorskip("litert_torch", reason="litert-torch (pip extra litert) is not installed")

import e3dpsm  # noqa: E402
from _edge_helpers import tflite_schema_graph  # noqa: E402
from _toy_litert_int8 import toy_feeds, toy_litert, toy_model  # noqa: E402
from e3dpsm.errors import ConfigError, DataError  # noqa: E402
from e3dpsm.export import litert_int8  # noqa: E402
from e3dpsm.export.edge_int8 import EdgeInt8Options  # noqa: E402
from e3dpsm.export.litert_export import LiteRTOptions  # noqa: E402
from e3dpsm.export.litert_int8 import (FLOAT_RULES, calibrate, choose_ranges, classify, group_patterns,  # noqa: E402
                                       mac_op_scopes, operator_units, quantised_activations, quantised_content)

TOY = "_toy_litert_int8"
STEM = r"torch\.nn\.modules\.conv\.Conv2d_stem(?=[/;]|$)"
GROUPS = [("model.stem", STEM), ("model.blocks", rf"{TOY}\.Block_\d(?=[/;]|$)")]
POSE_HEADS = "pose heads (mm outputs)"


@pytest.fixture(scope="module")
def content() -> bytes:
    return toy_litert()


def _scopes(content: bytes) -> dict[str, str]:
    """Short name -> scope of the toy's five operators, in graph order."""
    scopes = [scope for _, scope in mac_op_scopes(content)]
    assert len(scopes) == 5
    return dict(zip(("stem", "extra", "block0", "block1", "head"), scopes))


def test_the_operators_are_read_in_graph_order_with_their_activations_and_weights(content) -> None:
    found = litert_int8._mac_operators(content)
    assert [(op.name, op.weights) for op in found] == [("CONV_2D", 72), ("FULLY_CONNECTED", 16),
                                                       ("FULLY_CONNECTED", 32), ("FULLY_CONNECTED", 64),
                                                       ("FULLY_CONNECTED", 48)]
    schema, _, graph, codes = tflite_schema_graph(content)
    ops = [graph.Operators(i) for i in range(graph.OperatorsLength())]
    macs = [op for op in ops if codes[op.OpcodeIndex()] in ("CONV_2D", "FULLY_CONNECTED")]
    for op, read in zip(macs, found):
        names = [graph.Tensors(i).Name().decode() for i in (op.Inputs(0), *[op.Outputs(j) for j in
                                                                           range(op.OutputsLength())])]
        assert list(read.tensors) == names
    scopes = _scopes(content)
    assert "Conv2d_stem" in scopes["stem"] and "Linear_extra" in scopes["extra"]
    assert "Block_0" in scopes["block0"] and "Block_1" in scopes["block1"]
    assert "Linear_direct_head" in scopes["head"]


def test_each_operator_falls_in_one_group_under_a_rule_or_nowhere(content) -> None:
    scopes = _scopes(content)
    assert [litert_int8._place(s, GROUPS) for s in scopes.values()] == [
        ("group", "model.stem"), ("none", None), ("group", "model.blocks"), ("group", "model.blocks"),
        ("rule", POSE_HEADS)]
    assert classify(mac_op_scopes(content), GROUPS) == {
        "int8_candidates_by_group": {"model.stem": 1, "model.blocks": 2},
        "float_by_rule": {why: (1 if why == POSE_HEADS else 0) for _, why in FLOAT_RULES},
        "unmatched_float": [scopes["extra"]]}
    # a rule wins over a group that also matches
    assert litert_int8._place(scopes["head"], [("all", ".")]) == ("rule", POSE_HEADS)


def test_two_groups_claiming_one_operator_is_a_naming_clash(content) -> None:
    scopes = _scopes(content)
    both = [("a", rf"{TOY}\.Block_0(?=[/;]|$)"), ("b", rf"{TOY}\.Block_1(?=[/;]|$)")]
    assert litert_int8._place(scopes["block0"], both) == ("group", "a")
    with pytest.raises(ConfigError, match=r"matches groups \['a', 'b'\]: the group patterns overlap"):
        litert_int8._place(scopes["block1"], both)  # litert-torch names the fused output after both


@pytest.mark.parametrize("rule, scope", [
    ("S5 input drive and readouts (the recurrence)", "x/e3dpsm.layers.products.Projection_drive_re;1"),
    (POSE_HEADS, "x/torch.nn.modules.linear.Linear_delta_head;2"),
    (POSE_HEADS, "serving_default_pose_direct_output;"),
    ("embedding of the fused-pose state", "x/torch.nn.modules.container.Sequential_pose_embed/y;1"),
])
def test_the_keep_float_rules_name_the_recurrence_the_heads_and_the_embedding(rule, scope) -> None:
    assert litert_int8._place(scope, []) == ("rule", rule)
    assert litert_int8._place(scope.replace("_", "-"), []) == ("none", None)


def _weight_types(content: bytes) -> list[bool]:
    """Whether each CONV_2D / FULLY_CONNECTED weight is int8, read with the TFLite schema."""
    schema, _, graph, codes = tflite_schema_graph(content)
    ops = [graph.Operators(i) for i in range(graph.OperatorsLength())]
    return [graph.Tensors(op.Inputs(1)).Type() == schema.TensorType.INT8 for op in ops
            if codes[op.OpcodeIndex()] in ("CONV_2D", "FULLY_CONNECTED")]


def _calibration(count: int = 6, outlier: float = 0.0):
    return types.SimpleNamespace(feeds=toy_feeds(count, outlier))


@pytest.fixture(scope="module")
def qsvs(content):
    ranges, chosen, seconds = calibrate(content, _calibration(), GROUPS, threads=1)
    assert chosen["rule"] == "mse" and chosen["tensors"] == 5 and 0 < seconds < 60
    return ranges


@pytest.mark.parametrize("keep_float, int8", [
    ((), [True, False, True, True, False]),             # the groups' three; the unmatched and the head float
    (("model.blocks",), [True, False, False, False, False]),
    (("model.stem",), [False, False, True, True, False]),
])
def test_the_groups_not_kept_float_take_8_bit_weights(content, qsvs, keep_float, int8, capfd) -> None:
    before = copy.deepcopy(qsvs)
    quantised = quantised_content(content, qsvs, GROUPS, keep_float)
    assert capfd.readouterr() == ("", "")  # no progress bar or report: a search quantises hundreds of times
    assert _weight_types(quantised) == int8
    assert _weight_types(content) == [False] * 5
    assert repr(qsvs) == repr(before)  # the trial's copy took the quantizer's writes


def test_with_every_group_float_the_flatbuffer_is_returned_as_is(content, qsvs) -> None:
    assert litert_int8._recipe(content, GROUPS, ("model.stem", "model.blocks")) is None
    assert quantised_content(bytearray(content), qsvs, GROUPS, ("model.stem", "model.blocks")) == content
    assert isinstance(quantised_content(bytearray(content), qsvs, GROUPS, ("model.stem", "model.blocks")), bytes)


def test_the_quantizers_refusal_is_one_line(content, monkeypatch) -> None:
    with pytest.raises(DataError, match=r"^ai-edge-quantizer could not quantise the model: [^\n]+$"):
        quantised_content(content, {}, GROUPS)

    class Refusing:
        def quantize(self, *args, **kwargs):
            raise RuntimeError("r" * 400 + "\nsecond line")

    monkeypatch.setattr(litert_int8, "_recipe", lambda *args: Refusing())
    with pytest.raises(DataError) as error:
        quantised_content(content, {}, GROUPS)
    assert str(error.value) == "ai-edge-quantizer could not quantise the model: " + "r" * 300


def test_the_activations_take_the_calibrated_ranges(content, qsvs) -> None:
    """Each quantised activation's scale and zero point in the flatbuffer are the asymmetric
    8-bit ones of its range in `qsvs` (scale (max - min) / 255, zero point -128 - min / scale)."""
    schema, _, graph, _ = tflite_schema_graph(quantised_content(content, qsvs, GROUPS))
    tensors = {graph.Tensors(i).Name().decode(): graph.Tensors(i) for i in range(graph.TensorsLength())}
    checked = 0
    for name in quantised_activations(content, GROUPS):
        low, high = float(qsvs[name]["min"].item()), float(qsvs[name]["max"].item())
        coded = [t for n, t in tensors.items() if n == name and t.Type() == schema.TensorType.INT8]
        if not coded:
            continue
        q = coded[0].Quantization()
        scale = (high - low) / 255.0
        assert q.ScaleAsNumpy()[0] == pytest.approx(scale, rel=1e-5), name
        assert q.ZeroPointAsNumpy()[0] == pytest.approx(-128 - low / scale, abs=1.0), name
        checked += 1
    assert checked >= 3


def _toy_activations(feeds) -> dict[str, np.ndarray]:
    """The toy's activations by role, computed in PyTorch (the independent reference)."""
    model, seen = toy_model(), {}
    hooks = [model.stem.register_forward_hook(lambda m, i, o: seen.setdefault("stem_out", []).append(o)),
             model.blocks[0].register_forward_hook(lambda m, i, o: seen.setdefault("block0_in", []).append(i[0])),
             # litert-torch moves block 0's bias into block 1's (W1 (W0 h + b0) + b1 = W1 W0 h + (W1 b0 + b1)):
             # the flatbuffer's block-0 output is the product alone
             model.blocks[0].register_forward_hook(
                 lambda m, i, o: seen.setdefault("block0_out", []).append(o - m.ff_net.proj_in.bias)),
             model.blocks[1].register_forward_hook(lambda m, i, o: seen.setdefault("block1_out", []).append(o))]
    with torch.no_grad():
        for feed in feeds:
            model(torch.from_numpy(feed["x"]), torch.from_numpy(feed["s"]))
            seen.setdefault("x", []).append(torch.from_numpy(feed["x"]))
    for hook in hooks:
        hook.remove()
    return {k: torch.cat([t.flatten() for t in v]).numpy() for k, v in seen.items()}


def test_the_activations_to_range_are_the_groups_inputs_and_outputs_once_each(content) -> None:
    ops = litert_int8._mac_operators(content)
    stem, _, block0, block1, _ = ops
    assert quantised_activations(content, GROUPS) == [*stem.tensors, *block0.tensors, block1.tensors[1]]
    assert quantised_activations(content, [GROUPS[1]]) == [*block0.tensors, block1.tensors[1]]


def test_minmax_ranges_are_the_true_extremes_with_zero(content) -> None:
    feeds = toy_feeds(5)
    ranges, _, _ = calibrate(content, types.SimpleNamespace(feeds=feeds), GROUPS, threads=1, rule="minmax")
    qsvs = copy.deepcopy(ranges)
    names = quantised_activations(content, GROUPS)
    head = litert_int8._mac_operators(content)[4].tensors[1]  # a tensor of the graph the recipe has no range for
    assert head not in qsvs
    summary = choose_ranges(content, qsvs, names + ["not-a-tensor", head], feeds, threads=1, rule="minmax")
    assert summary == {"rule": "minmax", "tensors": 5, "narrowed": 0}
    want = _toy_activations(feeds)
    roles = dict(zip(("x", "stem_out", "block0_in", "block0_out", "block1_out"), names))
    for role, name in roles.items():
        values = want[role]
        low, high = min(float(values.min()), 0.0), max(float(values.max()), 0.0)
        np.testing.assert_allclose([qsvs[name]["min"].item(), qsvs[name]["max"].item()], [low, high], rtol=1e-5,
                                   atol=1e-6, err_msg=role)
        assert qsvs[name]["min"].shape == ranges[name]["min"].shape
    np.testing.assert_allclose(ranges[roles["x"]]["max"].item(), max(float(want["x"].max()), 0.0), rtol=1e-5)
    # the moving average ai-edge-quantizer keeps is inside the extremes for a tensor that varies
    assert ranges[roles["stem_out"]]["max"].item() <= qsvs[roles["stem_out"]]["max"].item() + 1e-6


def test_mse_ranges_come_from_histograms_over_the_true_extremes(content, monkeypatch) -> None:
    """The "mse" rule histograms each tensor over its true min-max range (with zero), every
    value of every feed counted once, and writes what choose_range picks (quantize/ranges.py,
    tested there); a pick that is not min-max counts as narrowed."""
    from e3dpsm.quantize import ranges as range_rules

    feeds = toy_feeds(5)
    names = quantised_activations(content, GROUPS)
    qsvs, _, _ = calibrate(content, types.SimpleNamespace(feeds=feeds), GROUPS, threads=1, rule="minmax")
    extremes = {n: (qsvs[n]["min"].item(), qsvs[n]["max"].item()) for n in names}
    seen = []

    def pick(hist):
        seen.append(hist)
        narrowed = len(seen) % 2 == 1  # every other tensor: its range halved
        high = hist.high / 2 if narrowed else hist.high
        return types.SimpleNamespace(kind="percentile" if narrowed else "minmax", low=hist.low, high=high)

    monkeypatch.setattr(range_rules, "choose_range", pick)
    summary = choose_ranges(content, qsvs, names, feeds, threads=1)  # "mse" by default
    assert summary == {"rule": "mse", "tensors": 5, "narrowed": 3}
    want = _toy_activations(feeds)
    sizes = {"x": want["x"].size, "stem_out": want["stem_out"].size, "block0_in": want["block0_in"].size,
             "block0_out": want["block0_out"].size, "block1_out": want["block1_out"].size}
    assert [int(h.counts.sum()) for h in seen] == list(sizes.values())
    assert [len(h.counts) for h in seen] == [range_rules.HISTOGRAM_BINS] * 5
    for k, (hist, name) in enumerate(zip(seen, names)):
        np.testing.assert_allclose([hist.low, hist.high], extremes[name], rtol=1e-6)
        high = extremes[name][1] / 2 if k % 2 == 0 else extremes[name][1]
        np.testing.assert_allclose([qsvs[name]["min"].item(), qsvs[name]["max"].item()], [extremes[name][0], high],
                                   rtol=1e-6)


def test_calibration_refuses_a_rule_it_does_not_know_and_feeds_for_another_model(content) -> None:
    with pytest.raises(ValueError, match="^range rule must be 'mse' or 'minmax', got 'max'$"):
        calibrate(content, _calibration(), GROUPS, threads=1, rule="max")
    wrong = types.SimpleNamespace(feeds=[{"y": np.zeros((1, 4), np.float32)}])
    with pytest.raises(DataError, match=r"^ai-edge-quantizer could not calibrate the model: [^\n]+$"):
        calibrate(content, wrong, GROUPS, threads=1)


def test_a_calibration_refusal_is_cut_to_300_characters(content, monkeypatch) -> None:
    class Refusing:
        def calibrate(self, *args, **kwargs):
            raise KeyError("k" * 400)

    monkeypatch.setattr(litert_int8, "_recipe", lambda *args: Refusing())
    with pytest.raises(DataError) as error:
        calibrate(content, _calibration(), GROUPS, threads=1)
    assert str(error.value) == "ai-edge-quantizer could not calibrate the model: '" + "k" * 299


def test_a_groups_units_are_its_operators_largest_first_each_matching_one_scope(content) -> None:
    scopes = _scopes(content)
    units = operator_units(content, GROUPS, "model.blocks")
    assert [label for label, _ in units] == ["model.blocks/1:fully_connected(ff_net.proj_in)",
                                             "model.blocks/0:fully_connected(ff_net.proj_in)"]
    for (_, pattern), name in zip(units, ("block1", "block0")):
        assert [n for n, s in scopes.items() if re.search(pattern, s)] == [name]
    assert operator_units(content, GROUPS, "model.stem") == [("model.stem/0:conv_2d", "^" + re.escape(
        scopes["stem"]) + "$")]


def test_the_tinys_groups_are_named_as_litert_torch_names_its_scopes() -> None:
    model = e3dpsm.create_model("tiny", height=32, width=64)
    look = "(?=[/;]|$)"
    step = re.escape("e3dpsm.export.wrapper.StepGraph_step/")
    want = [("model.stem", re.escape("torch.nn.modules.container.Sequential_stem") + look)]
    want += [(f"model.stages.{i}", re.escape(f"e3dpsm.layers.residual.EncoderStage_{i}") + look) for i in range(4)]
    want += [(f"model.attention.{i}", re.escape(f"e3dpsm.layers.deformable.DeformableTransformerBlock_{i}") + look)
             for i in range(4)]
    want += [("model.ssm", step + re.escape("e3dpsm.layers.feedforward.GEGLU_ff") + look),
             ("model.decoder", re.escape("e3dpsm.layers.decoder.JointQueryDecoder_decoder") + look)]
    assert group_patterns(model) == want
    stage = dict(want)["model.stages.1"]
    assert re.search(stage, "a/e3dpsm.layers.residual.EncoderStage_1/b;2")
    assert not re.search(stage, "a/e3dpsm.layers.residual.EncoderStage_12;2")


def test_a_trial_writes_the_quantised_flatbuffer_with_its_contract_and_opens_it(tmp_path, monkeypatch) -> None:
    opened = []
    monkeypatch.setattr(litert_int8, "embed_contract",
                        lambda content, model, litert, precision: (content + precision.encode(), {}))
    monkeypatch.setattr(litert_int8, "open_stepper",
                        lambda path, runtime, threads: opened.append((path.read_bytes(), path, runtime, threads))
                        or "STEPPER")
    trial = litert_int8._trial_opener("MODEL", lambda floats: ",".join(floats).encode(), tmp_path, LiteRTOptions(),
                                      EdgeInt8Options(threads=3))
    assert trial(["a", "b"]) == "STEPPER"
    assert opened == [(b"a,bint8", tmp_path / "trial.tflite", "litert", 3)]


def test_the_search_runs_over_the_groups_on_litert(tmp_path, monkeypatch) -> None:
    seen = {}
    monkeypatch.setattr(litert_int8, "search_float_groups", lambda groups, trial, search, options, runtime:
                        seen.update(groups=groups, search=search, runtime=runtime, trial=trial) or "PLACEMENT")
    monkeypatch.setattr(litert_int8, "_trial_opener", lambda *args: ("TRIAL", args))
    options = EdgeInt8Options()
    assert litert_int8.search_keep_float("MODEL", "Q", "SEARCH", options, GROUPS, tmp_path, "LT") == "PLACEMENT"
    assert seen == {"groups": ["model.stem", "model.blocks"], "search": "SEARCH", "runtime": "LiteRT (XNNPACK)",
                    "trial": ("TRIAL", ("MODEL", "Q", tmp_path, "LT", options))}


def test_narrowing_splits_the_kept_groups_of_several_operators_into_units(content, qsvs, tmp_path,
                                                                          monkeypatch) -> None:
    calls = {}

    def narrow(kept, units, trial, search, options, runtime):
        calls.update(kept=kept, units=units, search=search, runtime=runtime)
        calls["trial"] = trial(["model.stem", "model.blocks/1:fully_connected(ff_net.proj_in)"])
        return "NARROWING"

    monkeypatch.setattr(litert_int8, "narrow_float_groups", narrow)
    monkeypatch.setattr(litert_int8, "_trial_opener", lambda model, quantise, work, litert, options:
                        lambda floats: quantise(floats))
    fine, narrowing = litert_int8.narrow_keep_float("MODEL", content, qsvs, GROUPS, ["model.blocks", "model.stem"],
                                                    "SEARCH", EdgeInt8Options(), tmp_path, LiteRTOptions())
    units = operator_units(content, GROUPS, "model.blocks")
    assert narrowing == "NARROWING"
    assert fine == [GROUPS[0], *units]  # the stem's one operator is its own unit: not split
    assert calls["kept"] == ["model.blocks", "model.stem"]
    assert calls["units"] == {"model.blocks": [label for label, _ in units], "model.stem": ["model.stem/0:conv_2d"]}
    assert (calls["search"], calls["runtime"]) == ("SEARCH", "LiteRT (XNNPACK)")
    assert _weight_types(calls["trial"]) == [False, False, True, False, False]  # block 0 alone in 8 bits


class _Calibration(types.SimpleNamespace):
    def __len__(self) -> int:
        return len(self.feeds)


class Recorder:
    """convert_litert_int8's long parts recorded; the toy's flatbuffer stands for the step's."""

    def __init__(self, monkeypatch, content: bytes, float_groups: tuple[str, ...], narrowed: list[str] | None) -> None:
        self.calls: list[tuple] = []
        log = self.calls.append
        calibration = _Calibration(feeds=toy_feeds(4), state_source="fp32 rollout", seconds=1.5)
        placement = types.SimpleNamespace(float_nodes=float_groups)

        def narrow(model, float_content, qsvs, groups, kept, search, options, work, litert):
            log(("narrow", tuple(kept), search, work.parent))
            units = operator_units(float_content, groups, "model.blocks")
            fine = [GROUPS[0], *units]
            return fine, types.SimpleNamespace(floats=narrowed, search_fields=lambda blocks: {"blocks": list(blocks)})

        def write(content, model, path, litert, precision, seconds, record):
            log(("write", path, precision, _weight_types(content)))
            return types.SimpleNamespace(seconds=seconds, record=record)

        patches = {
            "fp32_reference": lambda model, work: log(("fp32_reference", work)) or "REF",
            "calibration_set": lambda ref, data, options: log(("calibration", ref)) or calibration,
            # 12 ms of conversion: a third decimal for the seconds' rounding to show
            "litert_content": lambda model, litert: log(("litert_content", litert)) or time.sleep(0.0123) or content,
            "group_patterns": lambda model: list(GROUPS),
            "search_set": lambda ref, data, options: log(("search_set", ref)) or time.sleep(0.0123) or "SEARCH",
            "search_keep_float": lambda model, quantise, search, options, groups, work, litert:
                log(("search", search, work.parent, work.name.startswith("e3dpsm-litert-search-"),
                     _weight_types(quantise(["model.stem"])))) or placement,
            "search_record": lambda placement, search, options, runtime: {"runtime": runtime},
            "narrow_keep_float": narrow,
            "write_litert": write,
            "held_out_set": lambda ref, data, options: log(("held_out", ref)) or "HELD",
            "check_artifact": lambda path, runtime, held, options: log(("check", path, runtime, held)) or "CHECK",
        }
        for name, value in patches.items():
            monkeypatch.setattr(litert_int8, name, value)


@pytest.mark.parametrize("rounds, narrow, float_groups, narrowed, int8", [
    (0, None, (), None, [True, False, True, True, False]),
    (1, None, (), None, [True, False, True, True, False]),
    (4, None, (), None, [True, False, True, True, False]),
    (4, None, ("model.blocks",), ["model.blocks/1:fully_connected(ff_net.proj_in)"], [True, False, True, False, False]),
    (4, 0, ("model.blocks",), None, [True, False, False, False, False]),
])
def test_convert_writes_and_judges_the_flatbuffer_its_search_chose(content, tmp_path, monkeypatch, rounds, narrow,
                                                                   float_groups, narrowed, int8) -> None:
    recorder = Recorder(monkeypatch, content, float_groups, narrowed)
    options = EdgeInt8Options(search_rounds=rounds, narrow_trials=narrow, threads=1)
    litert = LiteRTOptions(attention_form="gather")
    path = tmp_path / "step.tflite"
    result, check, held = litert_int8.convert_litert_int8("MODEL", "DATA", path, options, tmp_path, litert)
    assert (check, held) == ("CHECK", "HELD")
    searched, narrowing = rounds > 0, rounds > 0 and bool(float_groups) and narrow != 0
    expected = [("fp32_reference", tmp_path), ("calibration", "REF"), ("litert_content", litert)]
    if searched:
        expected += [("search_set", "REF"), ("search", "SEARCH", tmp_path, True, [False, False, True, True, False])]
    if narrowing:
        expected += [("narrow", float_groups, "SEARCH", tmp_path)]
    expected += [("write", path, "int8", int8), ("held_out", "REF"), ("check", path, "litert", "HELD")]
    assert recorder.calls == expected
    assert not [p for p in tmp_path.iterdir() if p.name.startswith("e3dpsm-litert-search-")]  # trials cleaned up
    record = result.record
    keep = narrowed if narrowing else list(float_groups) if searched else []
    assert record["keep_float"] == keep and record["int8_operators"] == sum(int8)
    assert record["operators"] == ["CONV_2D", "FULLY_CONNECTED"] and record["groups"] == dict(GROUPS)
    assert record["coverage"] == classify(mac_op_scopes(content), GROUPS)
    assert record["float_rules"] == [why for _, why in FLOAT_RULES]
    calibration = record["calibration"]
    assert {k: calibration[k] for k in ("split", "frames", "state_source")} == {
        "split": "train", "frames": 4, "state_source": "fp32 rollout"}
    assert calibration["ranges"] == {"rule": "mse", "tensors": 5, "narrowed": calibration["ranges"]["narrowed"]}
    assert 1.5 <= calibration["seconds"] < 60 and calibration["seconds"] == round(calibration["seconds"], 2)
    assert record["budget"] == options.budget.to_dict()
    assert record["quantizer"].startswith("ai-edge-quantizer static range")
    assert ("search" in record) is searched and ("blocks" in record.get("search", {})) is narrowing
    assert list(result.seconds) == ["convert", "calibrate", "search", "quantize"]
    assert all(0 <= v < 60 and v == round(v, 2) for v in result.seconds.values())


def test_without_the_extra_the_int8_converter_names_it_and_writes_nothing(tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(__import__("sys").modules, "ai_edge_quantizer", None)
    with pytest.raises(ConfigError, match=r'^ai_edge_quantizer is not installed \(to write INT8 .tflite models\): '
                                          r'pip install -e "\.\[litert\]"$'):
        litert_int8.convert_litert_int8("MODEL", "DATA", tmp_path / "s.tflite", EdgeInt8Options(), tmp_path)
    from e3dpsm.export import litert_weights8

    with pytest.raises(ConfigError, match=r'^ai_edge_quantizer is not installed \(to write INT8 .tflite models\): '):
        litert_weights8.convert_litert_weights8("MODEL", "DATA", tmp_path / "s.tflite", EdgeInt8Options(), tmp_path)
    assert list(tmp_path.iterdir()) == []


# The weight-only `.tflite` (export/litert_weights8.py) on the same toy.
def _weights_behind_dequantize(content: bytes) -> list[bool]:
    """Whether each CONV_2D / FULLY_CONNECTED reads its weight from a DEQUANTIZE of int8 codes."""
    schema, _, graph, codes = tflite_schema_graph(content)
    ops = [graph.Operators(i) for i in range(graph.OperatorsLength())]
    producers = {op.Outputs(0): op for op in ops}
    found = []
    for op in ops:
        if codes[op.OpcodeIndex()] in ("CONV_2D", "FULLY_CONNECTED"):
            source = producers.get(op.Inputs(1))
            found.append(source is not None and codes[source.OpcodeIndex()] == "DEQUANTIZE"
                         and graph.Tensors(source.Inputs(0)).Type() == schema.TensorType.INT8)
    return found


def test_weight_only_puts_every_operators_weights_in_8_bits_per_output_channel(content, capfd) -> None:
    """Every CONV_2D / FULLY_CONNECTED, groups and rules alike, reads int8 codes through a
    DEQUANTIZE with a scale per output channel, each weight within half a step of its float."""
    from e3dpsm.export.litert_weights8 import weight_only_content

    quantised = weight_only_content(content)
    assert capfd.readouterr() == ("", "")  # no progress bar or report
    assert _weights_behind_dequantize(quantised) == [True] * 5 and _weights_behind_dequantize(content) == [False] * 5
    schema, _, graph, codes = tflite_schema_graph(quantised)
    _, _, float_graph, float_codes = tflite_schema_graph(content)
    ops = [graph.Operators(i) for i in range(graph.OperatorsLength())]
    producers = {op.Outputs(0): op for op in ops}
    model = schema.Model.GetRootAs(quantised, 0)
    float_model = schema.Model.GetRootAs(content, 0)
    float_ops = [float_graph.Operators(i) for i in range(float_graph.OperatorsLength())
                 if float_codes[float_graph.Operators(i).OpcodeIndex()] in ("CONV_2D", "FULLY_CONNECTED")]
    macs = [op for op in ops if codes[op.OpcodeIndex()] in ("CONV_2D", "FULLY_CONNECTED")]
    for op, float_op in zip(macs, float_ops):
        dequantize = producers.get(op.Inputs(1))
        assert dequantize is not None and codes[dequantize.OpcodeIndex()] == "DEQUANTIZE"
        codes_tensor = graph.Tensors(dequantize.Inputs(0))
        assert codes_tensor.Type() == schema.TensorType.INT8
        q = codes_tensor.Quantization()
        rows = codes_tensor.ShapeAsNumpy()[0]
        assert q.ScaleLength() == rows and q.QuantizedDimension() == 0 and not q.ZeroPointAsNumpy().any()
        int8 = np.frombuffer(model.Buffers(codes_tensor.Buffer()).DataAsNumpy().tobytes(), np.int8)
        weight = float_graph.Tensors(float_op.Inputs(1))
        floats = np.frombuffer(float_model.Buffers(weight.Buffer()).DataAsNumpy().tobytes(), np.float32)
        scales = q.ScaleAsNumpy()[:, None]
        restored = int8.reshape(rows, -1) * scales
        assert np.all(np.abs(restored - floats.reshape(rows, -1)) <= scales / 2 + 1e-7)


def test_weight_only_refusals_are_one_line_naming_the_other_ways(content, monkeypatch) -> None:
    from ai_edge_quantizer import quantizer

    from e3dpsm.export.litert_weights8 import weight_only_content

    def refuse(self, **kwargs):
        raise RuntimeError("no such tensor\nsecond line")

    monkeypatch.setattr(quantizer.Quantizer, "quantize", refuse)
    with pytest.raises(ConfigError, match=r"^ai-edge-quantizer could not quantise this model's weights \(no such "
                                          r"tensor\); the fp32 `convert litert` or the static `--quantize int8` may "
                                          r"still convert it$"):
        weight_only_content(content)
    monkeypatch.setattr(quantizer.Quantizer, "quantize", lambda self, **kwargs: (_ for _ in ()).throw(ValueError()))
    with pytest.raises(ConfigError, match=r"weights \(ValueError\)"):
        weight_only_content(content)
    monkeypatch.setattr(quantizer.Quantizer, "quantize",
                        lambda self, **kwargs: (_ for _ in ()).throw(RuntimeError("w" * 400)))
    with pytest.raises(ConfigError, match=r"weights \(w{300}\); the fp32"):
        weight_only_content(content)


def test_weight_only_convert_writes_and_judges_without_calibration(content, tmp_path, monkeypatch) -> None:
    from e3dpsm.export import litert_weights8

    calls = []
    monkeypatch.setattr(litert_weights8, "fp32_reference", lambda model, work: calls.append(("ref", work)) or "REF")
    monkeypatch.setattr(litert_weights8, "litert_content", lambda model, litert: calls.append(("convert", litert))
                        or time.sleep(0.0123) or content)  # a third decimal for the rounding to show
    monkeypatch.setattr(litert_weights8, "write_litert", lambda c, model, path, litert, precision, seconds, record:
                        calls.append(("write", path, precision, _weights_behind_dequantize(c))) or
                        types.SimpleNamespace(seconds=seconds, record=record))
    monkeypatch.setattr(litert_weights8, "held_out_set", lambda ref, data, options: calls.append(("held", ref))
                        or "HELD")
    monkeypatch.setattr(litert_weights8, "check_artifact", lambda path, runtime, held, options:
                        calls.append(("check", path, runtime, held)) or "CHECK")
    options, litert, path = EdgeInt8Options(threads=1), LiteRTOptions(attention_form="gather"), tmp_path / "w.tflite"
    result, check, held = litert_weights8.convert_litert_weights8("MODEL", "DATA", path, options, tmp_path, litert)
    assert (check, held) == ("CHECK", "HELD")
    assert calls == [("ref", tmp_path), ("convert", litert), ("write", path, "int8-weights", [True] * 5),
                     ("held", "REF"), ("check", path, "litert", "HELD")]
    assert litert_weights8.RECIPE == ("ai-edge-quantizer weight-only: int8 weights symmetric per output channel, "
                                      "float activations and arithmetic")  # what convert.json tells a reader
    assert result.record == {"quantizer": litert_weights8.RECIPE, "operators": ["CONV_2D", "FULLY_CONNECTED"],
                             "int8_operators": 5, "arithmetic": "float", "budget": options.budget.to_dict()}
    assert list(result.seconds) == ["convert", "quantize"]
    assert all(0 < v < 60 and v == round(v, 2) for v in result.seconds.values())


class _SSMBlock(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.norm, self.gate, self.ff = torch.nn.LayerNorm(4), torch.nn.Linear(4, 4), torch.nn.Linear(4, 4)


class _FakeStep(torch.nn.Module):
    """The quantised scopes with an SSM dict whose blocks hold two linear children each."""

    def __init__(self) -> None:
        super().__init__()
        self.stem, self.stages, self.attention = torch.nn.Conv2d(1, 1, 1), torch.nn.ModuleList(), torch.nn.ModuleList()
        self.ssm = torch.nn.ModuleDict({"0": _SSMBlock(), "3": _SSMBlock()})
        self.decoder = torch.nn.Linear(4, 4)


def test_a_dict_of_blocks_is_named_by_its_members_called_children_in_one_alternation() -> None:
    """Children named alike in every block count once; the alternatives sorted, each under the
    step graph's own scope (the dict itself is never called)."""
    step = re.escape("e3dpsm.export.wrapper.StepGraph_step/")
    linear = re.escape("torch.nn.modules.linear.Linear")
    patterns = dict(group_patterns(_FakeStep()))
    assert patterns["model.ssm"] == f"{step}{linear}_ff(?=[/;]|$)|{step}{linear}_gate(?=[/;]|$)"
    for name in ("ff", "gate"):
        assert re.search(patterns["model.ssm"], f"e3dpsm.export.wrapper.StepGraph_step/torch.nn.modules.linear."
                                                f"Linear_{name};2")
    assert not re.search(patterns["model.ssm"], "e3dpsm.export.wrapper.StepGraph_step/torch.nn.modules.normalization."
                                                "LayerNorm_norm;1")


def test_classify_counts_every_operator_of_a_rule_and_a_group() -> None:
    scopes = [("FULLY_CONNECTED", "x/torch.nn.modules.linear.Linear_direct_head;1"),
              ("FULLY_CONNECTED", "x/torch.nn.modules.linear.Linear_delta_head;1"),
              ("CONV_2D", "x/torch.nn.modules.conv.Conv2d_stem;1"), ("CONV_2D", "x/torch.nn.modules.conv.Conv2d_stem;2"),
              ("FULLY_CONNECTED", "y/unknown;1")]
    assert classify(scopes, [GROUPS[0]]) == {
        "int8_candidates_by_group": {"model.stem": 2},
        "float_by_rule": {why: (2 if why == POSE_HEADS else 0) for _, why in FLOAT_RULES},
        "unmatched_float": ["y/unknown;1"]}
    long = "y/" + "u" * 400
    assert classify([("CONV_2D", long)], [])["unmatched_float"] == [long[:300]]


def test_an_overlap_names_the_scope_cut_to_200_characters() -> None:
    scope = "a/" + "b" * 300
    with pytest.raises(ConfigError) as error:
        litert_int8._place(scope, [("one", "a/"), ("two", "b{3}")])
    assert str(error.value) == f"operator scope {scope[:200]!r} matches groups ['one', 'two']: the group patterns overlap"


def test_units_of_equal_weights_keep_their_graph_order(monkeypatch) -> None:
    """Largest weights first; a tie keeps the order the operators run in (the narrowing tries
    the earlier one first)."""
    names = [("z_late", 8), ("a_early", 8), ("m_big", 16)] + [(f"n{k}", 8) for k in range(9)]  # 12: labels 10, 11
    found = [litert_int8.MacOperator("FULLY_CONNECTED", f"g/torch.nn.modules.linear.Linear_{name};1",
                                     ("in", f"g/torch.nn.modules.linear.Linear_{name};1"), weights)
             for name, weights in names]
    monkeypatch.setattr(litert_int8, "_mac_operators", lambda content: found)
    units = operator_units(b"", [("grp", "g(?=[/;]|$)")], "grp")
    assert [label for label, _ in units] == ["grp/2:fully_connected(m_big)", "grp/0:fully_connected(z_late)",
                                             "grp/1:fully_connected(a_early)"] + [
        f"grp/{k + 3}:fully_connected(n{k})" for k in range(9)]  # graph order, not the labels' (10 < 3)
