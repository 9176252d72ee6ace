"""The weight-only INT8 `.tflite` (export/litert_weights8.py): every CONV_2D / FULLY_CONNECTED
reads its weights through a DEQUANTIZE of constant 8-bit codes, symmetric per output channel,
and nothing else in the graph is quantised (no activation is ever rounded to a code, so its
arithmetic is float on any ISA). The codes are checked against the fp32 weights with numpy
(scale = max |w| / 127 per channel, codes within half a step), the artifact steps with float
outputs and states carried, its poses near fp32's, and `golden check` holds it to the
same-kind host tolerance on another ISA, where an INT8 artifact gets 0.5 mm.

The CLI end to end on the trained tiny (conversion and held-out budget) is slow."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from _edge_helpers import GOLDEN_STEPS, litert_pose_rollout, skip_without, tflite_schema_graph

WEIGHTED = ("CONV_2D", "FULLY_CONNECTED")


@pytest.fixture(scope="module")
def float_content(tflite_path) -> bytes:
    skip_without("ai_edge_quantizer")
    return tflite_path.read_bytes()


@pytest.fixture(scope="module")
def weights8_content(float_content) -> bytes:
    from e3dpsm.export.litert_weights8 import weight_only_content

    return weight_only_content(float_content)


def _buffer(model, tensor, dtype) -> np.ndarray:
    data = model.Buffers(tensor.Buffer())
    if data.Offset() > 1:  # stored past the flatbuffer (a model over 256 KiB of weights)
        raise AssertionError("external buffers are read by runtime/tflite_metadata, not here")
    return data.DataAsNumpy().view(dtype).reshape(tensor.ShapeAsNumpy())


def _weights(content: bytes) -> list[tuple[str, np.ndarray, np.ndarray | None]]:
    """(operator, float weights or 8-bit codes, per-channel scales or None) of every CONV_2D /
    FULLY_CONNECTED in graph order; a weight behind a DEQUANTIZE is read from its codes."""
    schema, model, graph, codes = tflite_schema_graph(content)
    producer = {graph.Operators(i).Outputs(j): graph.Operators(i) for i in range(graph.OperatorsLength())
                for j in range(graph.Operators(i).OutputsLength())}
    found = []
    for i in range(graph.OperatorsLength()):
        op = graph.Operators(i)
        if codes[op.OpcodeIndex()] not in WEIGHTED:
            continue
        weight = graph.Tensors(op.Inputs(1))
        source = producer.get(op.Inputs(1))
        if source is None:
            assert weight.Type() == schema.TensorType.FLOAT32
            found.append((codes[op.OpcodeIndex()], _buffer(model, weight, np.float32), None))
            continue
        assert codes[source.OpcodeIndex()] == "DEQUANTIZE"
        stored = graph.Tensors(source.Inputs(0))
        assert stored.Type() == schema.TensorType.INT8
        q = stored.Quantization()
        assert q.QuantizedDimension() == 0 and not q.ZeroPointAsNumpy().any()  # symmetric, per output channel
        found.append((codes[op.OpcodeIndex()], _buffer(model, stored, np.int8), q.ScaleAsNumpy()))
    return found


def test_every_weight_is_int8_per_output_channel_within_half_a_step(float_content, weights8_content) -> None:
    original, stored = _weights(float_content), _weights(weights8_content)
    assert len(stored) == len(original) > 0
    for (op, w, none), (op8, q, scale) in zip(original, stored):
        assert op == op8 and none is None and scale is not None and q.shape == w.shape
        flat = w.reshape(len(w), -1).astype(np.float64)
        expected = np.abs(flat).max(axis=1) / 127.0  # symmetric: the largest weight of a channel is code 127
        np.testing.assert_allclose(scale, expected, rtol=1e-6)
        error = np.abs(q.reshape(len(q), -1) * scale[:, None] - flat)
        assert np.all(error <= scale[:, None] / 2 * (1 + 1e-5)), op


def test_nothing_but_weights_is_quantised(weights8_content) -> None:
    """Float arithmetic: no QUANTIZE anywhere, every DEQUANTIZE reads a constant, and no
    operator writes 8- or 16-bit codes (a static INT8 recipe's QUANTIZE and integer kernels do)."""
    schema, model, graph, codes = tflite_schema_graph(weights8_content)
    codes_types = (schema.TensorType.INT8, schema.TensorType.UINT8, schema.TensorType.INT16)
    ops = [graph.Operators(i) for i in range(graph.OperatorsLength())]
    names = [codes[op.OpcodeIndex()] for op in ops]
    assert "QUANTIZE" not in names and names.count("DEQUANTIZE") == sum(n in WEIGHTED for n in names)
    for op, name in zip(ops, names):
        if name == "DEQUANTIZE":
            assert model.Buffers(graph.Tensors(op.Inputs(0)).Buffer()).DataLength() > 0  # a constant
        for j in range(op.OutputsLength()):
            assert graph.Tensors(op.Outputs(j)).Type() not in codes_types, name


def test_the_weight_only_artifact_steps_in_float_near_fp32(float_content, weights8_content, edge_model,
                                                          quant_data, tmp_path) -> None:
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export.litert_export import LiteRTOptions, embed_contract
    from e3dpsm.runtime.litert_session import LiteRTStepSession

    content, record = embed_contract(weights8_content, edge_model, LiteRTOptions(), "int8-weights")
    paths = {"weights8": tmp_path / "w8.tflite", "fp32": tmp_path / "fp32.tflite"}
    paths["weights8"].write_bytes(content)
    paths["fp32"].write_bytes(float_content)
    frames = np.asarray(PreparedData.open(quant_data).split("val")[0].lnes[:12], dtype=np.float32)
    rollouts = {name: litert_pose_rollout(path, frames) for name, path in paths.items()}
    assert LiteRTStepSession(paths["fp32"]).meta.quantization is None
    assert LiteRTStepSession(paths["weights8"]).meta.quantization["mode"] == "int8-weights"
    moved = np.linalg.norm(rollouts["weights8"] - rollouts["fp32"], axis=-1)
    assert 1e-3 < moved.max() < 20.0, moved.max()  # moved by the weights' rounding, not by activation codes


def test_golden_check_holds_it_to_the_same_kind_tolerance_on_another_isa(weights8_content, edge_model, edge_golden,
                                                                         tmp_path) -> None:
    """The host's rollout of the artifact moved by 0.05 mm and recorded on another ISA kind:
    an INT8 artifact would pass (0.5 mm across kinds), a float-arithmetic one fails (0.01)."""
    import shutil

    from e3dpsm.export.litert_export import LiteRTOptions, embed_contract
    from e3dpsm.golden.host import HOST_FOLDER, record_host_rollouts
    from e3dpsm.golden.store import MANIFEST_FILE
    from e3dpsm.golden.verify import verify_graph

    path = tmp_path / "w8.tflite"
    path.write_bytes(embed_contract(weights8_content, edge_model, LiteRTOptions(), "int8-weights")[0])
    golden = tmp_path / "golden"
    shutil.copytree(edge_golden, golden)
    record_host_rollouts(golden, [path], ["onnxruntime"], threads=1)
    assert verify_graph(path, golden, threads=1)[0].questions["same_as_host"] is True  # this host: the same
    manifest = json.loads((golden / MANIFEST_FILE).read_text())
    entry = manifest["host_rollouts"][-1]
    entry["isa"] = {**entry["isa"], "kind": "another"}
    (golden / MANIFEST_FILE).write_text(json.dumps(manifest))
    rollout = golden / entry["file"]
    arrays = dict(np.load(rollout))
    for name in arrays:
        arrays[name] = arrays[name] + np.float32(0.05)  # every joint 0.05 mm along each axis: 0.087 mm apart
    np.savez(rollout, **arrays)
    assert (golden / HOST_FOLDER).is_dir()
    result, report = verify_graph(path, golden, threads=1)
    host = next(t for t in result.tensors if t.measure == "host_distance_mm")
    assert host.mean == pytest.approx(0.05 * np.sqrt(3), rel=1e-3) and host.mean_limit == 0.01
    assert result.questions["same_as_host"] is False and not result.passed
    assert result.steps == GOLDEN_STEPS and report["model"]["quantization"]["mode"] == "int8-weights"


@pytest.mark.slow
def test_cli_writes_a_judged_weight_only_tflite(tmp_path, quant_data, capsys) -> None:
    skip_without("ai_edge_quantizer")
    from _quantize_helpers import TRAINED_TINY
    from e3dpsm.cli import main
    from e3dpsm.runtime.litert_session import tflite_metadata

    out = tmp_path / "w8"
    code = main(["convert", "litert", "--checkpoint", str(TRAINED_TINY), "--out", str(out),
                 "--quantize", "int8-weights", "--data", str(quant_data), "--threads", "1"])
    report = json.loads((out / "convert.json").read_text())
    assert code == 0 and report["budget"]["within"] and report["budget"]["frames"] > 0  # weights alone: within
    assert report["artifact"]["precision"] == "int8-weights" and report["artifact"]["arithmetic"] == "float"
    content = (out / "step.tflite").read_bytes()
    meta, record = tflite_metadata(out / "step.tflite", content)
    assert record["precision"] == "int8-weights" and meta.quantization["mode"] == "int8-weights"
    assert report["artifact"]["int8_operators"] == sum(scale is not None for *_, scale in _weights(content)) > 0
    assert report["size"]["int8_bytes"] == len(content)
    assert "float arithmetic" in capsys.readouterr().out


def test_weight_only_reads_the_held_out_split_alone(edge_model, quant_data) -> None:
    """No calibration and no search: a folder without those splits is enough for it, not for
    the static conversion."""
    from e3dpsm.errors import DataError
    from e3dpsm.export.edge_int8 import EdgeInt8Options, open_data

    options = EdgeInt8Options(split="calibration", search_split="search")  # neither is in the folder
    assert open_data(quant_data, edge_model, options, weights_only=True).split("test")
    with pytest.raises(DataError, match="no sequences in split 'calibration'"):
        open_data(quant_data, edge_model, options)
