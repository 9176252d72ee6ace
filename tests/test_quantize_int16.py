"""16-bit activations (`--target npu`): 16-bit activation QDQ runs on ONNX Runtime in the
default domain (opset 21) and is closer to fp32 than the same nodes at 8 bits; 16-bit tensors
take the calibration's min-max range widened; an NPU target's search places int16 nodes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from _quantize_helpers import fast


# -- on ONNX Runtime ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def int16_setup(tmp_path_factory, trained_graph: Path, quant_data: Path, calibrated_tiny: dict) -> dict:
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.graph_metadata import GraphMetadata
    from e3dpsm.quantize.graph_groups import recurrent_groups
    from e3dpsm.quantize.holdout import held_out

    model = onnx.load(str(calibrated_tiny["pre"]))
    keep = [n for g in recurrent_groups(model, GraphMetadata.from_onnx(model)) for n in g.nodes]
    holdout = held_out(trained_graph, PreparedData.open(quant_data).split("val"), 20.0, 40, "val", threads=1)
    kept = set(keep)
    compute = [n.name for n in model.graph.node if n.op_type in ("Conv", "MatMul", "Gemm") and n.name not in kept]
    return {"work": tmp_path_factory.mktemp("int16"), "pre": calibrated_tiny["pre"], "keep": keep,
            "cache": calibrated_tiny["cache"], "holdout": holdout, "compute": compute,
            "meta": GraphMetadata.from_onnx(onnx.load(str(trained_graph)))}


def _quantised(setup: dict, int16: list[str], name: str) -> tuple[Path, onnx.ModelProto]:
    from e3dpsm.quantize.artifact import finalize, save_model
    from e3dpsm.quantize.static import StaticConfig, quantize_int8

    out = setup["work"] / name
    quantize_int8(setup["pre"], out, StaticConfig(), exclude=setup["keep"], cache=setup["cache"], int16_nodes=int16)
    model = onnx.load(str(out))
    finalize(model, setup["meta"], {"mode": "int8"})
    save_model(model, out)
    return out, onnx.load(str(out))


def test_int16_nodes_run_on_onnx_runtime_closer_to_fp32_than_int8(int16_setup) -> None:
    from e3dpsm.quantize.holdout import distance_pct, graph_outputs

    # The CNN's convolutions (half the compute nodes) at 16-bit activations, the rest at 8.
    convs = [n for n in int16_setup["compute"] if "/stages." in n or "/stem/" in n]
    assert len(convs) >= 10
    path16, model16 = _quantised(int16_setup, convs, "int16.onnx")
    path8, model8 = _quantised(int16_setup, [], "int8.onnx")
    # Standard ONNX only: default-domain Q/DQ at opset 21, 16-bit zero points on those nodes' tensors.
    assert {n.domain for n in model16.graph.node} == {""}
    assert next(o.version for o in model16.opset_import if o.domain == "") == 21
    inits = {i.name: numpy_helper.to_array(i) for i in model16.graph.initializer}
    zp = {n.input[0]: inits[n.input[2]].dtype for n in model16.graph.node if n.op_type == "QuantizeLinear"}
    first_conv_input = next(n.input[0] for n in onnx.load(str(int16_setup["pre"])).graph.node if n.name == convs[0])
    assert zp[first_conv_input] == np.uint16
    assert sum(d == np.uint16 for d in zp.values()) >= len(convs) and any(d == np.uint8 for d in zp.values())
    # Fewer 8-bit tensors than the all-int8 graph, the same Q/DQ count.
    assert len([d for d in zp.values() if d == np.uint8]) < sum(1 for n in model8.graph.node if n.op_type == "QuantizeLinear")
    holdout = int16_setup["holdout"]
    err16 = distance_pct(graph_outputs(path16, holdout, threads=1), holdout)
    err8 = distance_pct(graph_outputs(path8, holdout, threads=1), holdout)
    # Measured on an AMD EPYC with AVX-512 VNNI: ~1.3% against 2.08%. Rounding 256x finer on
    # half the tensors must remove a clear share of the error on any CPU kind (int16 nodes
    # run in float arithmetic behind their DequantizeLinear; no VNNI dependence).
    assert err16 < 0.85 * err8, (err16, err8)


def test_int16_tensors_take_the_widened_min_max_range_under_mse_calibration(int16_setup, trained_graph: Path,
                                                                             quant_data: Path) -> None:
    """The mse ranges are chosen for 256 levels (clipping buys a finer step); at 65,536 levels
    clipping is all the error left, so 16-bit tensors get the calibration's full min-max range,
    widened INT16_RANGE_MARGIN times (unseen sequences go past the calibration's range)."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.quantize.calibration import record_calibration_set
    from e3dpsm.quantize.static import INT16_RANGE_MARGIN, StaticConfig, calibrate, minmax_cache_path, quantize_int8

    work = int16_setup["work"]
    calib = record_calibration_set(trained_graph, PreparedData.open(quant_data).split("train"), 16, 20.0, threads=1)
    cache = work / "cache_mse.json"
    chosen = calibrate(int16_setup["pre"], StaticConfig(calibration="mse"), calib, cache)
    minmax = json.loads(minmax_cache_path(cache).read_text())["data"]
    pre = onnx.load(str(int16_setup["pre"]))
    # A conv whose input range the mse rule narrowed: there the two rules differ.
    node, tensor = next((n.name, n.input[0]) for n in pre.graph.node
                        if n.name in int16_setup["compute"] and n.input[0] in chosen and chosen[n.input[0]].kind != "minmax")
    out = work / "mse16.onnx"
    quantize_int8(int16_setup["pre"], out, StaticConfig(calibration="mse"), exclude=int16_setup["keep"], cache=cache,
                  int16_nodes=[node])
    model = onnx.load(str(out))
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    q = next(n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == tensor)
    low, high = min(minmax[tensor]["lowest"]["data"][0], 0.0), max(minmax[tensor]["highest"]["data"][0], 0.0)
    low, high = low * INT16_RANGE_MARGIN, high * INT16_RANGE_MARGIN
    assert INT16_RANGE_MARGIN > 1.0
    assert inits[q.input[2]].dtype == np.uint16
    assert float(inits[q.input[1]]) == pytest.approx((high - low) / 65535, rel=1e-5)
    narrowed = (chosen[tensor].high - chosen[tensor].low) / 65535
    assert abs(float(inits[q.input[1]]) - narrowed) > 1e-3 * narrowed


@pytest.mark.parametrize("low, high, margin, expected", [
    (-1.0, 3.0, 2.0, (-2.0, 6.0)),
    (0.5, 4.0, 2.0, (0.0, 8.0)),      # zero joins the range first, as in every QDQ range
    (-3.0, -1.0, 1.5, (-4.5, 0.0)),
    (-1.0, 3.0, 1.0, (-1.0, 3.0)),
])
def test_widened_range(low: float, high: float, margin: float, expected: tuple[float, float]) -> None:
    from e3dpsm.quantize.static import widened_range

    assert widened_range(low, high, margin) == pytest.approx(expected)


def test_widened_range_refuses_a_margin_that_clips() -> None:
    from e3dpsm.quantize.static import widened_range

    with pytest.raises(ValueError, match="margin below 1"):
        widened_range(-1.0, 1.0, 0.5)


def test_int16_tensors_are_widened_under_minmax_calibration_too(tmp_path: Path) -> None:
    """Without an mse cache the calibration cache's own range is widened (it used to be
    written as it was, clipping unseen sequences)."""
    from e3dpsm.quantize.static import INT16_RANGE_MARGIN, int16_ranges

    cache = tmp_path / "calibration.json"
    cache.write_text(json.dumps({"data": {"a": {"lowest": {"data": [-0.5]}, "highest": {"data": [2.0]}},
                                          "b": {"lowest": {"data": [1.0]}, "highest": {"data": [3.0]}}}}))
    ranges = int16_ranges(cache, ["a", "b", "missing"])
    assert ranges == {"a": pytest.approx((-0.5 * INT16_RANGE_MARGIN, 2.0 * INT16_RANGE_MARGIN)),
                      "b": pytest.approx((0.0, 3.0 * INT16_RANGE_MARGIN))}




def test_an_npu_target_returns_nodes_at_16_bits_not_float(tmp_path, trained_graph, quant_data, int8_test_budget):
    """Under the test budget the full-integer graph fails (_quantize_helpers): on an NPU target
    the search's nodes take 16-bit activations (8-bit weights), on the CPU they return to float."""
    from e3dpsm.quantize import quantize_graph
    from e3dpsm.onnx_precision import compute_precisions

    report = quantize_graph(trained_graph, quant_data, tmp_path / "npu", fast(mode="int8", target="npu",
                                                                                 budget=int8_test_budget))
    placement = report["placement"]
    assert placement["int16_nodes"] and not placement["float_nodes"]
    assert all(t["int16_nodes"] == 0 for t in placement["trials"] if t["float_nodes"])  # float only as a fallback
    precisions = compute_precisions(onnx.load(str(tmp_path / "npu" / "step_int8.onnx")))
    assert all(precisions[n] == "int16" for n in placement["int16_nodes"])
    assert report["quantization"]["reduce_range"] is False  # an NPU's integer kernels: full 8-bit weights
