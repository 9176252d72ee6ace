"""The full-integer INT8 flow (per-tensor ranges, every Conv/MatMul/Gemm on 8-bit inputs,
16-bit activations where asked, learned ranges) on `paper` and on an imported `released`
checkpoint, at 64 x 96 so that each runs in seconds. No budget: the figures of these weights
mean nothing; the structure and the numbers' sanity do."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

import e3dpsm
from e3dpsm.data.prepare import prepare_dataset
from _quantize_helpers import fast
from tests.fixtures.released.weights import lightning_checkpoint, make_state_dict

FIXTURE = Path(__file__).parent / "fixtures" / "released"
SIZE = dict(height=64, width=96)
COMPUTE = ("Conv", "MatMul", "Gemm")


@pytest.fixture(scope="module")
def data64(quant_data, tmp_path_factory) -> Path:
    """The quantiser's synthetic sequences prepared again at 64 x 96."""
    out = tmp_path_factory.mktemp("data64") / "prepared"
    prepare_dataset(Path(quant_data).parent / "raw", out, window_ms=20.0, progress=False, **SIZE)
    return out


def _model(variant: str, work: Path) -> torch.nn.Module:
    model = e3dpsm.create_model(variant, **SIZE).eval()
    if variant == "released":  # the released layout's trained-like weights, read and imported as a user's
        from e3dpsm.importers import import_released, read_released_state_dict

        manifest = json.loads((FIXTURE / "manifest.json").read_text())
        torch.save(lightning_checkpoint(make_state_dict(manifest["layout"], manifest["seed"])), work / "epoch=14.ckpt")
        import_released(read_released_state_dict(work / "epoch=14.ckpt")[0], model)
    return model


def _reaches_compute(model: onnx.ModelProto, tensor: str) -> bool:
    """Does a Conv/MatMul/Gemm read `tensor`, through Q/DQ pairs and data-movement ops only?"""
    passing = {"QuantizeLinear", "DequantizeLinear", "Reshape", "Transpose", "Flatten", "Squeeze", "Unsqueeze"}
    readers = [n for n in model.graph.node if tensor in n.input]
    return any(n.op_type in COMPUTE or (n.op_type in passing and _reaches_compute(model, n.output[0]))
               for n in readers)


def _reads_8bit(model: onnx.ModelProto, node: onnx.NodeProto, inits: dict[str, onnx.TensorProto]) -> bool:
    """Whether the node's data and weight inputs both come out of a DequantizeLinear of 8-bit
    integers (the scale's zero point says the integer type)."""
    producer = {o: n for n in model.graph.node for o in n.output}
    for name in node.input[:2]:
        dq = producer.get(name)
        if dq is None or dq.op_type != "DequantizeLinear":
            return False
        zero_point = inits.get(dq.input[2]) if len(dq.input) > 2 else None
        quantised = inits.get(dq.input[0])
        dtype = (zero_point or quantised).data_type if (zero_point or quantised) is not None else None
        if dtype is None:  # an activation: its QuantizeLinear's zero point carries the type
            q = producer.get(dq.input[0])
            dtype = inits[q.input[2]].data_type if q is not None and len(q.input) > 2 else None
        if dtype not in (onnx.TensorProto.UINT8, onnx.TensorProto.INT8):
            return False
    return True


@pytest.mark.parametrize("variant", ["paper", "released"])
def test_full_integer_flow_on_paper_and_released(variant: str, data64: Path, tmp_path: Path) -> None:
    from e3dpsm.export import export_step
    from e3dpsm.quantize import quantize_graph
    from e3dpsm.onnx_precision import compute_precisions
    from e3dpsm.runtime import StepSession
    from e3dpsm.validation.streams import onnx_stream_outputs
    from e3dpsm.data.prepared import PreparedData

    graph = export_step(_model(variant, tmp_path), tmp_path / "step.onnx")
    report = quantize_graph(graph, data64, tmp_path / "int8", fast(mode="int8", exclude="none", calibration="mse",
                                                                     holdout_frames=20))
    model = onnx.load(str(tmp_path / "int8" / report["artifact"]))
    inits = {i.name: i for i in model.graph.initializer}
    compute = [n for n in model.graph.node if n.op_type in COMPUTE]
    assert compute and all(_reads_8bit(model, n, inits) for n in compute), \
        [n.name for n in compute if not _reads_8bit(model, n, inits)][:5]
    assert report["graph"]["fixed_float_nodes"] == 0 and set(compute_precisions(model).values()) == {"int8"}
    # The S5 readouts are quantised too, but read a copy of the new state: the state the graph
    # outputs and carries to the next step is the float one, never its 8-bit rounding.
    from e3dpsm.graph_metadata import GraphMetadata

    states = {s.output_name for s in GraphMetadata.from_onnx(model).states}
    assert report["graph"]["state_reads"]
    assert not {n.input[0] for n in model.graph.node if n.op_type == "QuantizeLinear"} & states
    producer = {o: n.op_type for n in model.graph.node for o in n.output}
    assert all(producer[s] != "DequantizeLinear" for s in states), {s: producer[s] for s in states}
    # MatMul and Gemm outputs no quantised op reads are left in float (--float-outputs matmul,
    # the default): a Gemm output keeps its Q/DQ pair only where a quantised op reads it through
    # data movement (attention's query and key projections), never the heads' or feed-forwards'.
    assert report["quantization"]["float_outputs"] == "matmul"
    gemm_outputs = {o for n in model.graph.node if n.op_type == "Gemm" for o in n.output}
    rounded = gemm_outputs & {n.input[0] for n in model.graph.node if n.op_type == "QuantizeLinear"}
    assert gemm_outputs - rounded and all(_reaches_compute(model, o) for o in rounded), \
        sorted(o for o in rounded if not _reaches_compute(model, o))
    assert report["calibration"]["ranges"]["won_by"]  # per-tensor choices were made
    check = report["check"]["by_runtime"]["onnxruntime"]
    assert np.isfinite(check["fidelity_mm"]) and check["fidelity_mm"] > 0
    # the INT8 graph streams a held-out sequence with finite poses near the fp32 ones
    lnes = np.asarray(PreparedData.open(data64).split("test")[0].lnes[:10], dtype=np.float32)
    fp32 = onnx_stream_outputs(StepSession(graph, threads=1), lnes, 20.0)["pose"]
    int8 = onnx_stream_outputs(StepSession(tmp_path / "int8" / report["artifact"], threads=1), lnes, 20.0)["pose"]
    assert np.all(np.isfinite(int8)) and 0 < np.abs(int8 - fp32).max() < 0.5 * np.abs(fp32).max()


@pytest.mark.parametrize("variant", ["paper", "released"])
def test_int16_nodes_on_paper_and_released(variant: str, data64: Path, tmp_path: Path) -> None:
    """16-bit activations on the first two convolutions: the graph goes to opset 21, those
    nodes read 16-bit tensors, every other compute node 8-bit."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.export import export_step
    from e3dpsm.quantize.calibration import record_calibration_set
    from e3dpsm.quantize.static import StaticConfig, ensure_opset, preprocess, quantize_int8

    graph = export_step(_model(variant, tmp_path), tmp_path / "step.onnx")
    pre = tmp_path / "pre.onnx"
    preprocess(graph, pre)
    ensure_opset(pre)
    convs = [n.name for n in onnx.load(str(pre)).graph.node if n.op_type == "Conv"][:2]
    calib = record_calibration_set(graph, PreparedData.open(data64).split("train"), 16, 20.0, threads=1)
    out = tmp_path / "int16.onnx"
    quantize_int8(pre, out, StaticConfig(), calibration=calib, cache=tmp_path / "cache.json", int16_nodes=convs)
    model = onnx.load(str(out))
    inits = {i.name: i for i in model.graph.initializer}
    producer = {o: n for n in model.graph.node for o in n.output}
    for node in model.graph.node:
        if node.op_type != "Conv":
            continue
        q = producer[producer[node.input[0]].input[0]]  # Conv <- DQ <- Q
        bits16 = inits[q.input[2]].data_type == onnx.TensorProto.UINT16
        assert bits16 == (node.name in convs), node.name
    from e3dpsm.runtime import StepSession
    from e3dpsm.validation.streams import onnx_stream_outputs

    lnes = np.asarray(PreparedData.open(data64).split("test")[0].lnes[:5], dtype=np.float32)
    assert np.all(np.isfinite(onnx_stream_outputs(StepSession(out, threads=1), lnes, 20.0)["pose"]))


@pytest.mark.parametrize("variant", ["paper", "released"])
def test_ranges_learned_with_the_weights_frozen_reach_the_full_integer_graph_on_paper_and_released(
        variant: str, data64: Path, tmp_path: Path) -> None:
    """`distill --qat --qat-full-integer --qat-ranges-only` on `paper` and an imported `released`
    (one step): a learned range for every tensor the full-integer graph quantises, the weights
    the teacher's, and `quantize --ranges-from-checkpoint` writes each range into that graph."""
    from e3dpsm.checkpoint import read_checkpoint, save_checkpoint
    from e3dpsm.cli import main
    from e3dpsm.export import export_step
    from e3dpsm.quantize import quantize_graph

    model = _model(variant, tmp_path)
    teacher = save_checkpoint(tmp_path / "teacher.pt", model)
    out = tmp_path / "ranges"
    assert main(["distill", "--teacher", str(teacher), "--student", str(teacher), "--data", str(data64),
                 "--out", str(out), "--steps", "1", "--seq-len", "3", "--batch-size", "1", "--warmup-steps", "1",
                 "--threads", "1", "--no-progress", "--qat", "--qat-full-integer", "--qat-ranges-only",
                 "--qat-calibration-windows", "2", "--causal"]) == 0
    payload = read_checkpoint(out / "checkpoint.pt")
    teacher_state = read_checkpoint(teacher)["model"]
    assert all(torch.equal(v, teacher_state[k]) for k, v in payload["model"].items())
    graph = export_step(model, tmp_path / "step.onnx")
    report = quantize_graph(graph, data64, tmp_path / "int8", fast(
        mode="int8", exclude="none", holdout_frames=20, ranges_from_checkpoint=str(out / "checkpoint.pt")))
    block = report["learned_ranges"]
    assert block["weights_frozen"] and block["calibrated_tensors"] == 0, block["uncovered"]
    learned = {(np.float32(q["scale"]), q["zero_point"]) for q in payload["qat_ranges"]["quantizers"]}
    written = onnx.load(str(tmp_path / "int8" / report["artifact"]))
    inits = {i.name: onnx.numpy_helper.to_array(i) for i in written.graph.initializer}
    activations = [n for n in written.graph.node if n.op_type == "QuantizeLinear" and n.input[0] not in inits]
    assert len(activations) >= block["learned_tensors"] * 0.9
    assert all((np.float32(inits[n.input[1]]), int(inits[n.input[2]])) in learned for n in activations)
