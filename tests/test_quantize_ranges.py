"""Per-tensor activation ranges (quantize/ranges.py, `quantize --calibration mse`).

References independent of the code: the expected error against the error of actually
quantising samples (numpy), the known MSE-optimal clipping of a Laplace distribution on
8 bits (Banner et al. 2019, "ACIQ": alpha* = 9.89 b), and ONNX Runtime's own QDQ scales
computed from the chosen range by the QuantizeLinear formula.
"""
from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.quantize.calibration import CalibrationSet
from e3dpsm.quantize.ranges import Histogram, choose_range, expected_squared_error
from e3dpsm.quantize.static import StaticConfig, calibrate, quantize_int8

LAPLACE_8BIT_OPTIMUM = 9.89  # ACIQ table, in units of the Laplace scale b


def _histogram(x: np.ndarray) -> Histogram:
    low, high = float(min(x.min(), 0.0)), float(max(x.max(), 0.0))
    return Histogram(np.histogram(x, 2048, range=(low, high))[0], low, high)


def _sample_mse(x: np.ndarray, low: float, high: float) -> float:
    """Quantise the samples themselves, as QuantizeLinear / DequantizeLinear do (U8)."""
    scale = (high - low) / 255.0
    zero = np.round(-low / scale)
    q = np.clip(np.round(x / scale) + zero, 0, 255)
    return float(np.mean(((q - zero) * scale - x) ** 2))


@pytest.fixture(scope="module")
def laplace() -> np.ndarray:
    x = np.random.default_rng(0).laplace(0.0, 1.0, 1_000_000)
    return np.concatenate([x, -x])  # symmetric, so the optimum is a symmetric clip


@pytest.mark.parametrize("low, high", [(-15.0, 15.0), (-9.89, 9.89), (-6.0, 6.0), (-3.0, 12.0)])
def test_expected_error_matches_quantising_the_samples(laplace, low, high) -> None:
    hist = _histogram(laplace)
    assert expected_squared_error(hist, low, high) == pytest.approx(_sample_mse(laplace, low, high), rel=0.06)


def test_laplace_range_lands_on_the_known_optimum(laplace) -> None:
    choice = choose_range(_histogram(laplace))
    assert choice.kind == "shrink" and choice.low == pytest.approx(-choice.high)
    # the shrink grid steps 8.7%: within half a step of the optimum
    assert choice.high == pytest.approx(LAPLACE_8BIT_OPTIMUM, rel=0.045)
    sweep = np.linspace(7.0, 13.0, 61)
    best = min(_sample_mse(laplace, -a, a) for a in sweep)
    assert _sample_mse(laplace, choice.low, choice.high) <= 1.01 * best
    assert choice.mse < 0.6 * choice.minmax_mse  # clipping pays on a heavy tail


def test_a_uniform_tensor_keeps_its_min_max_range() -> None:
    """No tail to clip: every narrower range costs more than it saves."""
    x = np.random.default_rng(1).uniform(0.0, 4.0, 200_000)
    choice = choose_range(_histogram(x))
    assert choice.kind == "minmax" and (choice.low, choice.high) == pytest.approx((0.0, 4.0), abs=1e-3)


def test_ranges_always_hold_zero() -> None:
    x = np.random.default_rng(2).normal(5.0, 0.1, 100_000)  # all positive, far from 0
    choice = choose_range(_histogram(x))
    assert choice.low == 0.0 and choice.high > 5.0


def _one_matmul_graph(path) -> None:
    """y = relu(x) @ W: the MatMul's input activation is what gets a range."""
    w = numpy_helper.from_array(np.random.default_rng(3).normal(size=(8, 4)).astype(np.float32), "w")
    graph = helper.make_graph(
        [helper.make_node("Relu", ["x"], ["h"], name="relu"), helper.make_node("MatMul", ["h", "w"], ["y"], name="mm")],
        "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", 8])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", 4])], [w])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8), str(path))


def test_chosen_range_reaches_the_qdq_graph(tmp_path) -> None:
    """The graph's activation scale and zero point are the chosen range's, by the U8 formula."""
    _one_matmul_graph(tmp_path / "g.onnx")
    rng = np.random.default_rng(4)
    # heavy-tailed activations: most small, a few large, so mse narrows the range
    # a Laplace tensor of 512k values: min-max spends its levels on a tail that is rare
    feeds = [{"x": rng.laplace(0, 1, (256, 8)).astype(np.float32)} for i in range(2000)]
    chosen = calibrate(tmp_path / "g.onnx", StaticConfig(calibration="mse"), CalibrationSet(feeds, "test"),
                       tmp_path / "cache.json")
    quantize_int8(tmp_path / "g.onnx", tmp_path / "q.onnx", StaticConfig(calibration="mse"), cache=tmp_path / "cache.json")
    model = onnx.load(str(tmp_path / "q.onnx"))
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    q = next(n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == "h")
    scale, zero = float(inits[q.input[1]]), int(inits[q.input[2]])
    c = chosen["h"]
    assert c.kind != "minmax" and c.high < 0.85 * max(float(f["x"].max()) for f in feeds)
    assert scale == pytest.approx((c.high - c.low) / 255.0, rel=1e-6) and zero == round(-c.low / scale)


@pytest.mark.parametrize("method", ["minmax", "entropy", "percentile"])
def test_ort_rules_calibrate_as_quantize_static_does(tmp_path, method) -> None:
    """calibrate() builds ONNX Runtime's calibrator itself (so that "mse" can start from its
    min-max ranges); for ORT's own rules it must give the ranges quantize_static computes
    when left to calibrate on its own: the same options, nothing silently changed."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, quantize_static
    from onnxruntime.quantization.calibrate import load_tensors_data

    from e3dpsm.quantize.calibration import FeedListReader

    _one_matmul_graph(tmp_path / "g.onnx")
    rng = np.random.default_rng(5)
    feeds = [{"x": rng.laplace(0, 1, (64, 8)).astype(np.float32)} for _ in range(50)]
    config = StaticConfig(calibration=method)
    calibrate(tmp_path / "g.onnx", config, CalibrationSet(feeds, "test"), tmp_path / "ours.json")
    ort_method = {"minmax": CalibrationMethod.MinMax, "entropy": CalibrationMethod.Entropy,
                  "percentile": CalibrationMethod.Percentile}[method]
    quantize_static(str(tmp_path / "g.onnx"), str(tmp_path / "q.onnx"), FeedListReader(feeds), quant_format=QuantFormat.QDQ,
                    op_types_to_quantize=list(config.op_types), calibrate_method=ort_method,
                    extra_options={"CalibPercentile": config.percentile}, calibration_cache_path=str(tmp_path / "ort.json"))
    ours, theirs = load_tensors_data(tmp_path / "ours.json"), load_tensors_data(tmp_path / "ort.json")
    assert set(ours) == set(theirs) and "h" in ours
    for name in ours:
        np.testing.assert_array_equal(np.ravel(ours[name].range_value), np.ravel(theirs[name].range_value))


@pytest.mark.parametrize("target, weight_limit", [("avx2", 64), ("other", 64), ("vnni", 127), ("dotprod", 127)])
def test_targets_without_int8_dot_products_get_7_bit_weights(tmp_path, target, weight_limit) -> None:
    """ONNX Runtime's non-VNNI U8S8 kernels add u8 x s8 product pairs in 16-bit saturating
    arithmetic: 7-bit weights (reduce_range) keep a pair inside 16 bits (255 * 64 * 2 < 2^15)."""
    from onnx import numpy_helper

    _one_matmul_graph(tmp_path / "g.onnx")
    feeds = [{"x": np.random.default_rng(6).laplace(0, 1, (16, 8)).astype(np.float32)} for _ in range(20)]
    config = StaticConfig.for_target(target)
    quantize_int8(tmp_path / "g.onnx", tmp_path / "q.onnx", config, calibration=CalibrationSet(feeds, "test"),
                  cache=tmp_path / "cache.json")
    model = onnx.load(str(tmp_path / "q.onnx"))
    weights = [numpy_helper.to_array(i) for i in model.graph.initializer if i.data_type == TensorProto.INT8]
    assert weights and max(int(np.abs(w.astype(np.int32)).max()) for w in weights) == weight_limit


def test_an_unknown_target_is_refused() -> None:
    from e3dpsm.errors import ConfigError

    with pytest.raises(ConfigError, match="unknown --target-isa 'arm'"):
        StaticConfig.for_target("arm")


def test_an_empty_histogram_keeps_its_range_and_stays_finite() -> None:
    """A tensor none of whose values fell in its histogram (seen on the untrained `paper`):
    its quantiles were NaN (0/0), and a NaN range reached the graph."""
    hist = Histogram(np.zeros(64), -2.0, 3.0)
    assert hist.quantile(1e-4) == -2.0 and hist.quantile(1.0 - 1e-4) == 3.0
    choice = choose_range(hist)
    assert np.isfinite(choice.low) and np.isfinite(choice.high) and choice.low <= 0.0 <= choice.high
