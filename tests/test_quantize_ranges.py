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
from e3dpsm.quantize.ranges import (
    PERCENTILES,
    Histogram,
    SHRINK_GRID,
    RangeChoice,
    candidate_ranges,
    choose_range,
    collect_histograms,
    expected_squared_error,
    select_ranges,
    summarise,
    with_zero,
)
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


@pytest.mark.parametrize("target, isa, weight_limit", [("avx2", "avx2", 64), ("other", "other", 64), ("vnni", "vnni", 127),
                                                       ("dotprod", "dotprod", 127), ("auto", "avx2", 64),
                                                       ("npu", "avx2", 127)])
def test_targets_without_int8_dot_products_get_7_bit_weights(tmp_path, target, isa, weight_limit) -> None:
    """ONNX Runtime's non-VNNI U8S8 kernels add u8 x s8 product pairs in 16-bit saturating
    arithmetic: 7-bit weights (reduce_range) keep a pair inside 16 bits (255 * 64 * 2 < 2^15).
    An NPU's integer kernels do not saturate so: 8-bit weights whatever the host."""
    from onnx import numpy_helper

    _one_matmul_graph(tmp_path / "g.onnx")
    feeds = [{"x": np.random.default_rng(6).laplace(0, 1, (16, 8)).astype(np.float32)} for _ in range(20)]
    config = StaticConfig.for_target(target, isa)
    quantize_int8(tmp_path / "g.onnx", tmp_path / "q.onnx", config, calibration=CalibrationSet(feeds, "test"),
                  cache=tmp_path / "cache.json")
    model = onnx.load(str(tmp_path / "q.onnx"))
    weights = [numpy_helper.to_array(i) for i in model.graph.initializer if i.data_type == TensorProto.INT8]
    assert weights and max(int(np.abs(w.astype(np.int32)).max()) for w in weights) == weight_limit


def test_an_unknown_target_is_refused() -> None:
    from e3dpsm.errors import ConfigError

    from e3dpsm.quantize import QuantizeOptions

    with pytest.raises(ConfigError, match="--target"):
        QuantizeOptions(target="arm")


def test_an_empty_histogram_keeps_its_range_and_stays_finite() -> None:
    """A tensor none of whose values fell in its histogram (seen on the untrained `paper`):
    its quantiles were NaN (0/0), and a NaN range reached the graph."""
    hist = Histogram(np.zeros(64), -2.0, 3.0)
    assert hist.quantile(1e-4) == -2.0 and hist.quantile(1.0 - 1e-4) == 3.0
    choice = choose_range(hist)
    assert np.isfinite(choice.low) and np.isfinite(choice.high) and choice.low <= 0.0 <= choice.high


# The checks below were written against survivors of `mutmut run --paths-to-mutate
# quantize/ranges.py` (2026-12-03): each pins one part of the error model or the histogram
# plumbing to a reference that does not go through the code (closed forms, numpy on the raw
# samples, an explicit loop).


@pytest.mark.parametrize("levels", [256, 65536])
def test_rounding_noise_is_a_step_squared_over_twelve(levels) -> None:
    """Values spread evenly inside the range: no clipping, and the error of rounding to a
    grid of `levels` points over [low, high] is step^2 / 12 with step = (high - low) /
    (levels - 1), the uniform-noise closed form (one level more or less is 0.8% off at 8 bits)."""
    x = np.random.default_rng(7).uniform(-1.0, 3.0, 2_000_000)
    hist = Histogram(np.histogram(x, 2048, range=(-1.0, 3.0))[0], -1.0, 3.0)
    step = 4.0 / (levels - 1)
    assert expected_squared_error(hist, -1.0, 3.0, levels) == pytest.approx(step**2 / 12.0, rel=1e-9)
    if levels == 256:  # and the default is the 8-bit grid
        assert expected_squared_error(hist, -1.0, 3.0) == pytest.approx(step**2 / 12.0, rel=1e-9)
        # the closed form is what quantising the samples gives
        assert expected_squared_error(hist, -1.0, 3.0) == pytest.approx(_sample_mse(x, -1.0, 3.0), rel=0.005)


def test_clipping_error_is_the_squared_distance_to_the_range() -> None:
    """Values outside the range cost their squared distance to its nearer end (explicit loop
    over the bins); values inside cost the rounding noise."""
    counts = np.zeros(40, np.int64)
    counts[[0, 3, 20, 37, 39]] = [5, 2, 100, 1, 7]
    hist = Histogram(counts, -4.0, 6.0)  # bins 0.25 wide
    low, high = -3.0, 5.0
    centres = -4.0 + 0.25 * (np.arange(40) + 0.5)
    step = (high - low) / 255
    total = 0.0
    for n, c in zip(counts, centres):
        if low <= c <= high:
            total += n * step**2 / 12
        else:
            total += n * (c - (low if c < low else high)) ** 2
    assert expected_squared_error(hist, low, high) == pytest.approx(total / counts.sum(), rel=1e-12)


def test_quantiles_are_the_samples_quantiles() -> None:
    """Histogram.quantile against numpy's quantile of the values it counts, within a bin."""
    x = np.random.default_rng(8).normal(1.0, 2.0, 400_000)
    hist = _histogram(x)
    width = (hist.high - hist.low) / len(hist.counts)
    for q in (1e-4, 0.01, 0.25, 0.5, 0.9, 0.999):
        assert hist.quantile(q) == pytest.approx(float(np.quantile(x, q)), abs=width)
    assert hist.quantile(0.0) == hist.low and hist.quantile(1.0) == hist.high


@pytest.mark.parametrize("counts, q, expected", [
    ([1, 1, 1, 1], 0.5, 2.0), ([1, 1, 1, 1], 0.25, 1.0),   # even counts: the bin edges
    ([0, 0, 2, 2], 0.5, 3.0), ([0, 0, 2, 2], 0.25, 2.5),   # empty first bins
    ([0, 0, 0, 4], 0.5, 3.5),                              # all in the last bin
    ([4, 0, 0, 0], 0.5, 0.5), ([2, 2, 0, 0], 0.25, 0.5),   # all in the first bins
])
def test_quantiles_interpolate_within_a_bin(counts, q, expected) -> None:
    """On [0, 4] in four bins: the cumulative count, linear within each bin."""
    assert Histogram(np.array(counts), 0.0, 4.0).quantile(q) == pytest.approx(expected, abs=1e-12)


def test_percentile_candidates_clip_both_tails_at_the_stated_mass() -> None:
    """Each PERCENTILES entry p gives the range between the samples' (100 - p)% and p%
    quantiles: 99.99 keeps all but 0.01% of the values, split between the two tails."""
    x = np.random.default_rng(9).laplace(0.5, 1.0, 1_000_000)
    hist = _histogram(x)
    width = (hist.high - hist.low) / len(hist.counts)
    percentile = [(p, low, high) for kind, p, low, high in candidate_ranges(hist) if kind == "percentile"]
    assert [p for p, _, _ in percentile] == list(PERCENTILES) == [99.9, 99.99, 99.999]
    for p, low, high in percentile:
        tail = (100.0 - p) / 100.0
        assert low == pytest.approx(float(np.quantile(x, tail)), abs=width)
        assert high == pytest.approx(float(np.quantile(x, 1.0 - tail)), abs=width)


def test_shrink_candidates_scale_the_min_max_ends() -> None:
    hist = Histogram(np.ones(16, np.int64), -2.0, 8.0)
    kinds = {(kind, p): (low, high) for kind, p, low, high in candidate_ranges(hist)}
    f = SHRINK_GRID[len(SHRINK_GRID) // 2]
    assert kinds[("shrink", f)] == pytest.approx((-2.0 * f, 8.0 * f))
    assert kinds[("shrink_high", f)] == pytest.approx((-2.0, 8.0 * f))
    assert kinds[("shrink_low", f)] == pytest.approx((-2.0 * f, 8.0))
    assert kinds[("minmax", 1.0)] == (-2.0, 8.0)


@pytest.mark.parametrize("low, high, expected", [(-2.0, -1.0, (-2.0, 0.0)), (0.2, 0.5, (0.0, 0.5)),
                                                 (-1.0, 3.0, (-1.0, 3.0))])
def test_with_zero_widens_only_to_hold_zero(low, high, expected) -> None:
    assert with_zero(low, high) == expected


def _relu_values(feeds: list[dict[str, np.ndarray]]) -> np.ndarray:
    """Every value the one-MatMul graph's quantised activation h = relu(x) takes, by numpy."""
    return np.concatenate([np.maximum(f["x"], 0.0).ravel() for f in feeds])


def test_histograms_count_every_feed(tmp_path) -> None:
    """collect_histograms over several feeds: the counts of np.histogram of all the values
    the tensor took (here relu(x), computed by numpy), on its min-max range widened to 0."""
    _one_matmul_graph(tmp_path / "g.onnx")
    rng = np.random.default_rng(10)
    feeds = [{"x": rng.normal(0.5, 1.0, (32, 8)).astype(np.float32)} for _ in range(3)]
    relu = _relu_values(feeds)
    low, high = float(relu.min()), float(relu.max())
    hist = collect_histograms(tmp_path / "g.onnx", {"h": (low, high)}, feeds, bins=64)["h"]
    assert (hist.low, hist.high) == (0.0, high)
    np.testing.assert_array_equal(hist.counts, np.histogram(relu, 64, range=(0.0, high))[0])
    assert hist.counts.sum() == relu.size


def test_summary_counts_the_winners_and_the_median_gain() -> None:
    def choice(kind: str, mse: float, minmax: float) -> RangeChoice:
        return RangeChoice(kind, 1.0, 0.0, 1.0, mse, minmax)

    chosen = {"a": choice("shrink", 1.0, 4.0), "b": choice("minmax", 2.0, 2.0), "c": choice("shrink", 1.0, 2.0),
              "d": choice("percentile", 0.0, 0.0)}
    assert summarise(chosen) == {"tensors": 4, "won_by": {"minmax": 1, "percentile": 1, "shrink": 2},
                                 "median_mse_ratio_to_minmax": 0.5}  # ratios 0.25, 1, 0.5; d has none
    assert summarise({})["median_mse_ratio_to_minmax"] == 1.0
    assert summarise({"a": choice("shrink", 0.1, 0.4)})["median_mse_ratio_to_minmax"] == pytest.approx(0.25)


def test_choices_are_scored_on_the_8_bit_grid_by_default(tmp_path) -> None:
    """choose_range's and select_ranges' default is the U8 grid: the chosen range's error is
    the 256-level expected error, as the model's written scale (range / 255) makes it."""
    x = np.random.default_rng(11).laplace(0.0, 1.0, 200_000)
    hist = _histogram(x)
    chosen = choose_range(hist)
    assert chosen.mse == expected_squared_error(hist, chosen.low, chosen.high, 256)
    _one_matmul_graph(tmp_path / "g.onnx")
    feeds = [{"x": np.random.default_rng(12).laplace(0, 1, (64, 8)).astype(np.float32)} for _ in range(4)]
    relu = _relu_values(feeds)
    minmax = {"h": (float(relu.min()), float(relu.max()))}
    selected = select_ranges(tmp_path / "g.onnx", minmax, feeds)["h"]
    assert selected == choose_range(collect_histograms(tmp_path / "g.onnx", minmax, feeds)["h"], 256)


def test_a_tensor_that_is_always_zero_has_an_empty_histogram(tmp_path) -> None:
    """relu of negative inputs: the range is [0, 0] and nothing is counted (np.histogram
    would otherwise invent a bin around 0); its error is nil."""
    _one_matmul_graph(tmp_path / "g.onnx")
    feeds = [{"x": -np.abs(np.random.default_rng(13).normal(size=(16, 8))).astype(np.float32) - 0.1}]
    hist = collect_histograms(tmp_path / "g.onnx", {"h": (0.0, 0.0)}, feeds, bins=32)["h"]
    assert hist.counts.sum() == 0 and (hist.low, hist.high) == (0.0, 0.0)
    assert expected_squared_error(hist, 0.0, 0.0) == 0.0
    assert expected_squared_error(Histogram(np.zeros(8, np.int64), -1.0, 1.0), -1.0, 1.0) == 0.0
