"""The INT8 `.tflite` (export/litert_int8.py): ai-edge-quantizer's static recipe placed on the
fp32 flatbuffer by operator scope. Every convolution and fully connected operator lands in a
search group or under a keep-float rule (none unplaced), the rules keep exactly the recurrent
projections, the pose heads and the fused-pose embedding float (counted on the PyTorch model,
not on the flatbuffer), a kept-float group keeps float weights, and the 8-bit flatbuffer
steps through LiteRT with float outputs and states carried.

The CLI end to end (conversion, search, held-out budget) on the trained tiny is slow: the
fp32 conversion alone takes over a minute on two cores."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from _edge_helpers import Judged, litert_pose_rollout, skip_without, tflite_schema_graph

TINY_GROUPS = ["model.stem", "model.stages.0", "model.stages.1", "model.stages.2", "model.stages.3",
               "model.attention.0", "model.attention.1", "model.attention.2", "model.attention.3",
               "model.ssm", "model.decoder"]


@pytest.fixture(scope="module")
def float_content(tflite_path) -> bytes:
    skip_without("ai_edge_quantizer")
    return tflite_path.read_bytes()


@pytest.fixture(scope="module")
def ranges(float_content, edge_model, trained_graph, quant_data):
    """Calibration of the full 8-bit recipe on 16 train frames with their rollout states."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export.litert_int8 import calibrate, group_patterns
    from e3dpsm.quantize.calibration import record_calibration_set

    data = PreparedData.open(quant_data)
    calibration = record_calibration_set(trained_graph, data.split("train"), 16, data.window_ms, threads=1)
    qsvs, _, _ = calibrate(float_content, calibration, group_patterns(edge_model), threads=1)
    return qsvs


def _weight_types(content: bytes) -> list[tuple[str, str, bool]]:
    """(operator, scope, weight is int8) of every CONV_2D / FULLY_CONNECTED, read with the
    TFLite schema directly (not through the quantizer's own utilities)."""
    schema, _, graph, codes = tflite_schema_graph(content)
    found = []
    for i in range(graph.OperatorsLength()):
        op = graph.Operators(i)
        name = codes[op.OpcodeIndex()]
        if name in ("CONV_2D", "FULLY_CONNECTED"):
            weight = graph.Tensors(op.Inputs(1))
            scope = ";".join(graph.Tensors(op.Outputs(j)).Name().decode() for j in range(op.OutputsLength()))
            found.append((name, scope, weight.Type() == schema.TensorType.INT8))
    return found


def test_mse_ranges_narrow_the_quantised_activations_inside_min_max(float_content, edge_model, trained_graph,
                                                                    quant_data, ranges) -> None:
    """The chosen ranges replace the calibration's min-max ranges of the activations the 8-bit
    operators read and write: each inside its min-max range (widened to hold 0), many narrower."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export.litert_int8 import calibrate, group_patterns, quantised_activations
    from e3dpsm.quantize.calibration import record_calibration_set

    data = PreparedData.open(quant_data)
    calibration = record_calibration_set(trained_graph, data.split("train"), 16, data.window_ms, threads=1)
    groups = group_patterns(edge_model)
    minmax, rule, _ = calibrate(float_content, calibration, groups, threads=1, rule="minmax")
    assert rule["rule"] == "minmax" and rule["narrowed"] == 0 and rule["tensors"] > 0
    names = quantised_activations(float_content, groups)
    assert len(names) > 2 * len(groups)
    # "minmax" is the calibration's true extremes, found here by a loop of our own (the
    # quantizer's calibration keeps a moving average, which would sit inside them).
    from ai_edge_litert.interpreter import Interpreter

    interpreter = Interpreter(model_content=float_content, num_threads=1, experimental_preserve_all_tensors=True)
    runner = interpreter.get_signature_runner()
    index = {d["name"]: d["index"] for d in interpreter.get_tensor_details()}
    probe = names[:: max(1, len(names) // 6)]
    seen = {n: [] for n in probe}
    for feed in calibration.feeds:
        runner(**{k: np.ascontiguousarray(v) for k, v in feed.items()})
        for n in probe:
            seen[n].append(interpreter.get_tensor(index[n]).copy())
    for n in probe:
        values = np.concatenate([v.ravel() for v in seen[n]])
        assert float(np.min(minmax[n]["min"])) == pytest.approx(min(float(values.min()), 0.0), abs=1e-6), n
        assert float(np.max(minmax[n]["max"])) == pytest.approx(max(float(values.max()), 0.0), abs=1e-6), n
    narrower = 0
    for name in names:
        low, high = float(np.min(ranges[name]["min"])), float(np.max(ranges[name]["max"]))
        raw_low, raw_high = min(float(np.min(minmax[name]["min"])), 0.0), max(float(np.max(minmax[name]["max"])), 0.0)
        assert raw_low - 1e-6 <= low <= 0.0 <= high <= raw_high + 1e-6, name
        narrower += (high - low) < 0.99 * (raw_high - raw_low)
    assert narrower >= len(names) // 4, (narrower, len(names))


def test_every_mac_operator_has_a_place(float_content, edge_model) -> None:
    from e3dpsm.export.litert_int8 import FLOAT_RULES, classify, group_patterns, mac_op_scopes
    from e3dpsm.layers.products import Projection
    from e3dpsm.layers.s5 import S5

    groups = group_patterns(edge_model)
    assert [name for name, _ in groups] == TINY_GROUPS
    placed = classify(mac_op_scopes(float_content), groups)
    assert placed["unmatched_float"] == []
    assert all(count > 0 for count in placed["int8_candidates_by_group"].values()), placed
    # The keep-float rules, counted on the PyTorch model: each S5 layer's projections, the two
    # heads, the fused-pose embedding's linear layers.
    projections = sum(isinstance(m, Projection) for s5 in edge_model.modules() if isinstance(s5, S5)
                      for m in s5.modules())
    embed = sum(isinstance(m, torch.nn.Linear) for m in edge_model.pose_embed.modules())
    expected = dict(zip((why for _, why in FLOAT_RULES), (projections, 2, embed)))
    assert placed["float_by_rule"] == expected
    total = sum(placed["int8_candidates_by_group"].values()) + sum(expected.values())
    assert total == len(_weight_types(float_content))


def test_a_groups_operator_units_name_one_operator_each(float_content, edge_model, ranges) -> None:
    """The narrowing's units: one per MAC operator of the group (as many as classify counts),
    each pattern matching that operator's scope and no other, largest weights first (read from
    the flatbuffer with the schema), labelled by the module path below the group; a unit kept
    float keeps exactly its operator's weights float."""
    import re

    from e3dpsm.export.litert_int8 import classify, group_patterns, mac_op_scopes, operator_units, quantised_content

    groups = group_patterns(edge_model)
    units = operator_units(float_content, groups, "model.attention.3")
    scopes = [scope for _, scope in mac_op_scopes(float_content)]
    assert len(units) == classify(mac_op_scopes(float_content), groups)["int8_candidates_by_group"]["model.attention.3"]
    matched = [[scope for scope in scopes if re.search(pattern, scope)] for _, pattern in units]
    assert all(len(m) == 1 for m in matched) and len({m[0] for m in matched}) == len(units)
    sizes = _weight_sizes(float_content)
    assert [sizes[m[0]] for m in matched] == sorted((sizes[m[0]] for m in matched), reverse=True)
    labels = [label for label, _ in units]
    assert all(label.startswith("model.attention.3/") for label in labels)
    assert {"fully_connected(ff.proj_in)", "fully_connected(ff.proj_out)", "conv_2d(proj_in)",
            "conv_2d(proj_out)"} <= {label.split(":", 1)[1] for label in labels}
    fine = [(n, p) for n, p in groups if n != "model.attention.3"] + units
    kept = units[0]
    ops = _weight_types(quantised_content(float_content, ranges, fine, (kept[0],)))
    assert [f"{scope};" for _, scope, q in ops if not q and "Block_3" in scope] == matched[0]


def _weight_sizes(content: bytes) -> dict[str, int]:
    """scope -> elements of the weight tensor of every CONV_2D / FULLY_CONNECTED."""
    from ai_edge_litert import schema_py_generated as schema

    model = schema.Model.GetRootAs(content, 0)
    graph = model.Subgraphs(0)
    sizes = {}
    for i in range(graph.OperatorsLength()):
        op = graph.Operators(i)
        if op.InputsLength() > 1 and op.Inputs(1) >= 0:
            scope = "".join(graph.Tensors(op.Outputs(j)).Name().decode() + ";" for j in range(op.OutputsLength()))
            sizes[scope] = int(np.prod(graph.Tensors(op.Inputs(1)).ShapeAsNumpy()))  # the quantizer's scope form
    return sizes


def test_short_tensor_names_change_nothing_but_names_and_size(float_content, tmp_path) -> None:
    """What `convert litert` writes by default: every tensor renamed s<subgraph>t<index>, the
    signature's names, the metadata and the outputs (to the bit, over steps with the states
    carried) unchanged, the file smaller by at least half of what the old names weighed."""
    from ai_edge_litert import schema_py_generated as schema

    from e3dpsm.runtime.litert_session import LiteRTStepSession
    from e3dpsm.runtime.tflite_metadata import is_short_tensor_name, read_metadata, with_short_tensor_names

    short = with_short_tensor_names(float_content)
    graphs = {name: schema.ModelT.InitFromPackedBuf(bytearray(c), 0) for name, c in
              (("long", float_content), ("short", short))}
    names = {k: [t.name.decode() for t in m.subgraphs[0].tensors] for k, m in graphs.items()}
    assert names["short"] == [f"s0t{i}" for i in range(len(names["long"]))]
    assert all(map(is_short_tensor_name, names["short"])) and not any(map(is_short_tensor_name, names["long"]))
    assert not is_short_tensor_name("s0t12_quantized")
    assert len(float_content) - len(short) > 0.5 * (sum(map(len, names["long"])) - sum(map(len, names["short"])))
    signature = {k: [(t.name, t.tensorIndex) for t in m.signatureDefs[0].inputs + m.signatureDefs[0].outputs]
                 for k, m in graphs.items()}
    assert signature["long"] == signature["short"]
    assert read_metadata(short) == read_metadata(float_content)
    rollouts = {}
    for name, content in (("long", float_content), ("short", short)):
        (tmp_path / f"{name}.tflite").write_bytes(content)
        session = LiteRTStepSession(tmp_path / f"{name}.tflite", threads=1)
        state, frames = session.init_state(1), np.random.default_rng(0).random((4, 1, *session.meta.frame_input["shape"][1:]))
        poses = []
        for frame in frames.astype(np.float32):
            out, state = session.step(frame, state, 20.0)
            poses.append(out["pose"])
        rollouts[name] = np.stack(poses)
    assert np.array_equal(rollouts["long"], rollouts["short"])


def test_narrowing_a_kept_group_within_its_trial_cap(float_content, edge_model, ranges, tmp_path,
                                                     monkeypatch) -> None:
    """narrow_keep_float on the tiny's attention 3 with --narrow-trials 2 and a judge that
    wants only its second-largest operator float: the two largest are tried (the first goes
    back to 8 bits, the second stays float), the rest stay float untried; the flatbuffer
    quantised with what is left float has exactly those operators' weights float (read from
    the file), and every other operator of the group in 8 bits."""
    import re

    from e3dpsm.export import edge_int8, litert_int8
    from e3dpsm.export.litert_export import LiteRTOptions

    groups = litert_int8.group_patterns(edge_model)
    units = litert_int8.operator_units(float_content, groups, "model.attention.3")
    assert len(units) >= 4

    def float_ops(content: bytes) -> set[str]:
        """The units whose operator keeps float weights in `content` (weight types read with
        the TFLite schema, scopes as the quantizer names them, both in graph order)."""
        scopes = [op.scope for op in litert_int8._mac_operators(content) if op.name in ("CONV_2D", "FULLY_CONNECTED")]
        weights = _weight_types(content)
        assert len(scopes) == len(weights)
        return {label for label, pattern in units for scope, (_, _, int8) in zip(scopes, weights)
                if not int8 and re.match(pattern, scope)}

    monkeypatch.setattr(litert_int8, "open_stepper", lambda path, _runtime, _threads: Path(path).read_bytes())
    monkeypatch.setattr(edge_int8, "check_stepper",
                        lambda content, _search, _budget: Judged(units[1][0] in float_ops(content)))
    fine, narrowing = litert_int8.narrow_keep_float(
        edge_model, float_content, ranges, groups, ["model.attention.3"], None,
        edge_int8.EdgeInt8Options(narrow_trials=2), tmp_path, LiteRTOptions(keep_tensor_names=True))  # judged by scope
    labels = [label for label, _ in units]
    assert [(t["unit"], t["within"]) for t in narrowing.trials] == [(labels[0], True), (labels[1], False)]
    assert narrowing.floats == labels[1:] and narrowing.untried == labels[2:]
    assert "model.attention.3" not in dict(fine) and set(labels) <= set(dict(fine))
    written = litert_int8.quantised_content(float_content, ranges, fine, narrowing.floats)
    assert float_ops(written) == set(labels[1:])
    assert sum(int8 for *_, int8 in _weight_types(written)) == sum(int8 for *_, int8 in _weight_types(
        litert_int8.quantised_content(float_content, ranges, groups, ()))) - (len(labels) - 1)


def test_the_code_trace_exposes_every_quantize_and_names_where_codes_part(float_content, edge_model, ranges,
                                                                           edge_golden, tmp_path) -> None:
    """e3dpsm/golden/tflite_trace.py: the copy that hands out every QUANTIZE output computes
    the same poses to the bit; two records of it on one machine never part; a device record
    with one code tensor's digest changed from step 2 on is named as the first to part, at
    step 2 (and a later one at a later step is not); traces of two graphs are refused."""
    from ai_edge_litert import schema_py_generated as schema

    from e3dpsm.export.litert_export import LiteRTOptions, embed_contract
    from e3dpsm.export.litert_int8 import group_patterns, quantised_content
    from e3dpsm.golden import tflite_trace
    from e3dpsm.golden.store import load_golden
    from e3dpsm.runtime.litert_session import LiteRTStepSession

    content, _ = embed_contract(quantised_content(float_content, ranges, group_patterns(edge_model)), edge_model,
                                LiteRTOptions(), "int8")
    exposed, codes = tflite_trace.with_exposed_codes(content)
    model = schema.ModelT.InitFromPackedBuf(bytearray(content), 0)
    names = {v: k for k, v in vars(schema.BuiltinOperator).items() if not k.startswith("_")}
    quantize = [i for i, op in enumerate(model.subgraphs[0].operators)
                if names[max(model.operatorCodes[op.opcodeIndex].builtinCode,
                              model.operatorCodes[op.opcodeIndex].deprecatedBuiltinCode)] == "QUANTIZE"]
    assert [c["operator"] for c in codes] == quantize and quantize
    assert all(set(c["read_by"]) <= {"CONV_2D", "FULLY_CONNECTED", "BATCH_MATMUL"} and c["read_by"] for c in codes)
    golden = load_golden(edge_golden)
    poses = {}
    for name, data in (("original", content), ("exposed", exposed)):
        (tmp_path / f"{name}.tflite").write_bytes(data)
        session = LiteRTStepSession(tmp_path / f"{name}.tflite", threads=1)
        state, out = session.init_state(1), []
        for step in range(6):
            result, state = session.step(golden.frame(step), state, golden.window_ms(step))
            out.append(result["pose"])
        poses[name] = np.stack(out)
    assert np.array_equal(poses["original"], poses["exposed"])
    (tmp_path / "step_int8.tflite").write_bytes(content)
    host = tflite_trace.record(tmp_path / "step_int8.tflite", edge_golden, steps=6)
    assert host["steps"] == 6 and len(host["digests"]) == 6 and len(host["digests"][0]) == len(codes)
    same = tflite_trace.compare(host, tflite_trace.record(tmp_path / "step_int8.tflite", edge_golden, steps=6))
    assert same["first_step"] is None and same["apart_by_end"] == 0 and "same at every one" in tflite_trace.summary(same)
    device = json.loads(json.dumps(host))
    for step in range(2, 6):
        device["digests"][step][3] = "0" * 16
    for step in range(4, 6):
        device["digests"][step][1] = "0" * 16
    apart = tflite_trace.compare(host, device)
    assert apart["first_step"] == 2 and [c["name"] for c in apart["first_departures"]] == [codes[3]["name"]]
    assert apart["apart_by_end"] == 2 and apart["per_code"][1]["first_step"] == 4
    assert f"step 2, first in graph order {codes[3]['name']} (operator {codes[3]['operator']}" in tflite_trace.summary(apart)
    # A kept module-path name is shown (its first scope, tail); a short one says nothing more.
    code = {**codes[3], "tensor_name": "a/b.Block_0/Linear_proj;12_quantized", "fed_by": "ADD",
            "read_by": ["FULLY_CONNECTED"]}
    assert tflite_trace.describe(code) == (f"{code['name']} (operator {code['operator']}: ADD -> QUANTIZE -> "
                                           "FULLY_CONNECTED, a/b.Block_0/Linear_proj)")
    assert tflite_trace.describe({**code, "tensor_name": "s0t1521"}).endswith("-> FULLY_CONNECTED)")
    with pytest.raises(ValueError, match="different graphs"):
        tflite_trace.compare(host, {**device, "codes": device["codes"][1:]})


def test_the_code_trace_command_refuses_bad_input_in_one_line(tmp_path, capsys) -> None:
    from e3dpsm.golden.tflite_trace import main

    assert main(["compare", str(tmp_path / "host.json"), str(tmp_path / "device.json")]) == 2
    (tmp_path / "not.tflite").write_bytes(b"not a flatbuffer")
    assert main(["record", str(tmp_path / "not.tflite"), str(tmp_path), str(tmp_path / "out.json")]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 2 and all(e.startswith("tflite_trace: error: ") for e in errors)
    assert "TFL3" in errors[1] and not (tmp_path / "out.json").exists()


def test_overlapping_group_patterns_are_refused() -> None:
    from e3dpsm.errors import ConfigError
    from e3dpsm.export.litert_int8 import classify

    scopes = [("CONV_2D", "a/EncoderStage_1/Conv2d_conv1")]
    with pytest.raises(ConfigError, match="overlap"):
        classify(scopes, [("one", r"EncoderStage_1"), ("two", r"Conv2d_conv1")])


def test_a_kept_float_group_keeps_float_weights(float_content, edge_model, ranges) -> None:
    from e3dpsm.export.litert_int8 import group_patterns, quantised_content

    groups = group_patterns(edge_model)
    kept = dict(groups)["model.stages.1"]
    ops = _weight_types(quantised_content(float_content, ranges, groups, ("model.stages.1",)))
    import re

    in_kept = [q for _, scope, q in ops if re.search(kept, scope)]
    assert in_kept and not any(in_kept)  # every stage-1 operator reads float weights
    every = _weight_types(quantised_content(float_content, ranges, groups))
    assert sum(q for *_, q in every) - sum(q for *_, q in ops) == len(in_kept)  # only those changed
    assert not any(q for _, scope, q in every if "Projection_" in scope or "direct_head" in scope)


def test_the_int8_flatbuffer_steps_with_float_outputs_and_states(float_content, edge_model, ranges,
                                                                 quant_data, tmp_path) -> None:
    """A quantised head output or a state the rewrite left dangling (both happened with an
    unrestricted recipe) fails here: every output float32, twelve frames stepped with the
    states carried, the poses moved by the 8 bits but within a few cm of the fp32 model's."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export.litert_export import LiteRTOptions, embed_contract
    from e3dpsm.export.litert_int8 import group_patterns, quantised_content

    content, record = embed_contract(quantised_content(float_content, ranges, group_patterns(edge_model)),
                                     edge_model, LiteRTOptions(), "int8")
    assert record["precision"] == "int8"
    path = tmp_path / "step_int8.tflite"
    path.write_bytes(content)
    frames = np.asarray(PreparedData.open(quant_data).split("val")[0].lnes[:12], dtype=np.float32)
    (tmp_path / "fp32.tflite").write_bytes(float_content)
    moved = np.linalg.norm(litert_pose_rollout(path, frames) - litert_pose_rollout(tmp_path / "fp32.tflite", frames),
                           axis=-1)
    assert 0.01 < moved.max() < 50.0, moved.max()


@pytest.mark.parametrize("fmt, extra, expected", [
    ("litert", ["--quantize", "int8"], "--quantize int8 needs --data"),
    ("litert", ["--data", "DATA"], "--data is read only with --quantize;"),
    ("litert", ["--quantize", "int8-weights"], "--quantize int8-weights needs --data"),
    ("executorch", ["--quantize", "int8-weights"], "--quantize int8-weights is written for litert only"),
])
def test_cli_refuses_bad_quantize_arguments_in_one_line(fmt, extra, expected, tmp_path, capsys) -> None:
    skip_without("ai_edge_quantizer")
    from _quantize_helpers import TRAINED_TINY
    from e3dpsm.cli import main

    out = tmp_path / "lt8"
    extra = [str(tmp_path) if arg == "DATA" else arg for arg in extra]
    assert main(["convert", fmt, "--checkpoint", str(TRAINED_TINY), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and expected in err and not out.exists()


@pytest.mark.slow
def test_cli_writes_a_judged_int8_tflite(tmp_path, quant_data, capsys) -> None:
    skip_without("ai_edge_quantizer")
    from _quantize_helpers import TRAINED_TINY
    from e3dpsm.cli import main
    from e3dpsm.runtime.litert_session import tflite_metadata

    out = tmp_path / "lt8"
    code = main(["convert", "litert", "--checkpoint", str(TRAINED_TINY), "--out", str(out), "--quantize", "int8",
                 "--data", str(quant_data), "--frames", "16", "--threads", "1"])
    report = json.loads((out / "convert.json").read_text())
    assert code == (0 if report["budget"]["within"] else 1)
    assert report["format"] == "litert" and report["budget"]["frames"] > 0
    assert report["artifact"]["coverage"]["unmatched_float"] == []
    assert report["artifact"]["search"]["trials"][0]["label"] == "all-int8"
    assert report["size"]["int8_bytes"] == (out / "step.tflite").stat().st_size
    _, record = tflite_metadata(out / "step.tflite", (out / "step.tflite").read_bytes())
    assert record["precision"] == "int8" and record["keep_float"] == report["artifact"]["keep_float"]
    # The 8-bit operator count convert.json records, against the weights in the file itself.
    weights = _weight_types((out / "step.tflite").read_bytes())
    assert report["artifact"]["int8_operators"] == sum(q for *_, q in weights) > 0
    assert "held-out frames" in capsys.readouterr().out
    assert all(scope.startswith("s0t") for _, scope, _ in weights)  # the default short tensor names


def _with_external_buffer(content: bytes) -> bytes:
    """`content` with its largest buffer stored past the flatbuffer (offset and size), the
    layout ai-edge-quantizer writes for models with more than 256 KiB of weights."""
    import flatbuffers
    from ai_edge_litert import schema_py_generated as schema

    model = schema.ModelT.InitFromPackedBuf(bytearray(content), 0)
    index = max(range(len(model.buffers)), key=lambda i: len(model.buffers[i].data if model.buffers[i].data is not None else ()))
    data = bytes(bytearray(model.buffers[index].data))
    model.buffers[index].data = None

    def pack(offset: int) -> bytes:
        model.buffers[index].offset, model.buffers[index].size = offset, len(data)
        builder = flatbuffers.Builder(len(content))
        builder.Finish(model.Pack(builder), file_identifier=b"TFL3")
        return bytes(builder.Output())

    head = pack(1 << 40)  # fixed-width fields: the length does not depend on the value
    offset = (len(head) + 15) & ~15
    head = pack(offset)
    assert offset >= len(head)
    return head + b"\0" * (offset - len(head)) + data


def test_metadata_goes_into_a_model_with_external_buffers(float_content, tmp_path) -> None:
    from e3dpsm.runtime.tflite_metadata import read_metadata, with_metadata
    from ai_edge_litert.interpreter import Interpreter

    external = _with_external_buffer(float_content)
    rewritten = with_metadata(external, "e3dpsm", b'{"layout": 2}')
    assert read_metadata(rewritten)["e3dpsm"] == b'{"layout": 2}'
    assert read_metadata(rewritten).keys() == read_metadata(float_content).keys()
    outputs = []
    for content in (float_content, external, rewritten):
        runner = Interpreter(model_content=content, num_threads=1).get_signature_runner()
        feeds = {k: np.full(v["shape"], 0.5, v["dtype"]) for k, v in runner.get_input_details().items()}
        outputs.append(runner(**feeds)["pose"])
    np.testing.assert_array_equal(outputs[1], outputs[0])  # the external layout is the same model
    np.testing.assert_array_equal(outputs[2], outputs[0])  # and so is the rewrite
