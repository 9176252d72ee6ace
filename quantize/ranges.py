"""Activation ranges chosen per tensor (`quantize --calibration mse`).

ONNX Runtime's calibrators apply one rule to every tensor: min-max keeps every outlier (a
sharp, outlier-heavy activation then gets a coarse step everywhere), a percentile clips
every tensor at the same tail mass whether its tail matters or not. Here each activation
that will be quantised gets its own range: from a histogram of its calibration values, the
range with the lowest expected squared quantisation error of that tensor (its rounding noise
inside the range plus its clipping error outside), chosen among min-max, the percentile
ranges and a grid of narrower ranges. That is MSE-optimal clipping (as in Banner et al.
2019, "ACIQ", and NVIDIA's pytorch-quantization `mse` calibrator), per tensor.

The chosen ranges go into ONNX Runtime's calibration cache as a min-max `TensorsData`, so
`quantize_static` writes them unchanged into an ordinary QDQ graph (no custom ops, no
override machinery), and the exclusion searches re-quantise from the same cache.

Model of the error, per histogram bin of width w at centre c holding n values, for an
asymmetric unsigned range [lo, hi] on L levels (step s = (hi - lo) / (L - 1)):
- c inside [lo, hi]: n * s^2 / 12 (uniform rounding noise);
- c outside: n * (c - clip(c, lo, hi))^2 (clipping; its rounding noise is nil).
ONNX Runtime widens every range to hold 0 (so that 0 is exact); candidates do too.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import onnx

from e3dpsm.onnx_graph import with_outputs

HISTOGRAM_BINS = 2048
PERCENTILES: tuple[float, ...] = (99.9, 99.99, 99.999)
# Narrower ranges tried besides min-max and the percentiles: the min-max range's ends pulled
# towards 0 to these fractions (both ends, and each end alone for one-sided tails).
SHRINK_GRID: tuple[float, ...] = tuple(np.round(np.geomspace(0.02, 1.0, 48), 5))
# The least relative drop of the expected error, against min-max, that narrows a range.
MIN_GAIN = 0.01


@dataclass(frozen=True)
class Histogram:
    """Counts of a tensor's calibration values over `HISTOGRAM_BINS` equal bins of [low, high]
    (its min-max range, widened to hold 0)."""

    counts: np.ndarray
    low: float
    high: float

    @property
    def edges(self) -> np.ndarray:
        return np.linspace(self.low, self.high, len(self.counts) + 1)

    @property
    def centres(self) -> np.ndarray:
        e = self.edges
        return 0.5 * (e[:-1] + e[1:])

    def quantile(self, q: float) -> float:
        """Value below which a fraction q of the counts lies (linear within a bin); the range's
        own end for an empty histogram (a tensor whose values never came), which has no quantiles."""
        cdf = np.concatenate([[0.0], np.cumsum(self.counts, dtype=np.float64)])
        if cdf[-1] == 0:
            return self.high if q >= 0.5 else self.low
        cdf /= cdf[-1]
        return float(np.interp(q, cdf, self.edges))


def with_zero(low: float, high: float) -> tuple[float, float]:
    """ONNX Runtime's rule: a quantised range always holds 0 exactly."""
    return min(low, 0.0), max(high, 0.0)


def expected_squared_error(hist: Histogram, low: float, high: float, levels: int = 256) -> float:
    """Mean squared quantisation error of the histogram's values on [low, high] (module docstring)."""
    low, high = with_zero(low, high)
    total = float(hist.counts.sum())
    if total == 0 or high <= low:
        return 0.0
    c = hist.centres
    step = (high - low) / (levels - 1)
    inside = (c >= low) & (c <= high)
    rounding = hist.counts[inside].sum() * step**2 / 12.0
    clipped = float(np.sum(hist.counts[~inside] * (c[~inside] - np.clip(c[~inside], low, high)) ** 2))
    return (rounding + clipped) / total


@dataclass(frozen=True)
class RangeChoice:
    kind: str      # "minmax", "percentile" (both tails), "shrink" (both ends), "shrink_high", "shrink_low"
    param: float   # the percentile, or the fraction of the min-max end kept; 1.0 for minmax
    low: float
    high: float
    mse: float     # expected squared error on the calibration histogram
    minmax_mse: float  # the same for the min-max range, for the report


def candidate_ranges(hist: Histogram) -> list[tuple[str, float, float, float]]:
    """(kind, param, low, high) candidates: min-max first, the percentiles, the shrink grid."""
    out = [("minmax", 1.0, hist.low, hist.high)]
    for p in PERCENTILES:
        tail = (100.0 - p) / 100.0
        out.append(("percentile", p, hist.quantile(tail), hist.quantile(1.0 - tail)))
    for f in SHRINK_GRID:
        out += [("shrink", f, hist.low * f, hist.high * f), ("shrink_high", f, hist.low, hist.high * f),
                ("shrink_low", f, hist.low * f, hist.high)]
    return out


def choose_range(hist: Histogram, levels: int = 256) -> RangeChoice:
    """The candidate with the lowest expected squared error, if it beats min-max by at least
    MIN_GAIN: a range is narrowed only where that measurably pays, not on histogram noise."""
    (kind, param, low, high), *others = candidate_ranges(hist)
    minmax = expected_squared_error(hist, low, high, levels)
    keep = best = RangeChoice(kind, float(param), *with_zero(low, high), minmax, minmax)
    for kind, param, low, high in others:
        err = expected_squared_error(hist, low, high, levels)
        if err < best.mse:
            best = RangeChoice(kind, float(param), *with_zero(low, high), err, minmax)
    return keep if best.mse > (1.0 - MIN_GAIN) * minmax else best


def collect_histograms(model_path: str | os.PathLike, ranges: Mapping[str, tuple[float, float]],
                       feeds: Sequence[Mapping[str, np.ndarray]], bins: int = HISTOGRAM_BINS) -> dict[str, Histogram]:
    """Histograms of the named tensors over the calibration feeds, on their min-max ranges."""
    import onnxruntime as ort

    model = with_outputs(onnx.load(str(model_path)), ranges)
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    wanted = list(ranges)
    bounds = {n: with_zero(*ranges[n]) for n in wanted}
    counts = {n: np.zeros(bins, np.int64) for n in wanted}
    for feed in feeds:
        values = dict(zip(wanted, session.run(wanted, dict(feed))))
        for name in wanted:
            low, high = bounds[name]
            if high > low:
                counts[name] += np.histogram(values[name].ravel(), bins=bins, range=(low, high))[0]
    return {n: Histogram(counts[n], *bounds[n]) for n in wanted}


def select_ranges(model_path: str | os.PathLike, minmax: Mapping[str, tuple[float, float]],
                  feeds: Sequence[Mapping[str, np.ndarray]], levels: int = 256) -> dict[str, RangeChoice]:
    """The chosen range of every tensor in `minmax` (its calibration min-max range)."""
    return {name: choose_range(hist, levels) for name, hist in collect_histograms(model_path, minmax, feeds).items()}


def write_minmax_cache(cache: str | os.PathLike, chosen: Mapping[str, RangeChoice]) -> None:
    """The chosen ranges as ONNX Runtime's min-max calibration cache (quantize_static reads it)."""
    from onnxruntime.quantization.calibrate import CalibrationMethod, TensorsData, save_tensors_data

    data = {n: (np.float32(c.low), np.float32(c.high)) for n, c in chosen.items()}
    save_tensors_data(TensorsData(CalibrationMethod.MinMax, data), cache)


def summarise(chosen: Mapping[str, RangeChoice]) -> dict:
    """How many tensors each kind of candidate won, and by how much it lowered the expected
    error against min-max (median ratio)."""
    won: dict[str, int] = {}
    for c in chosen.values():
        won[c.kind] = won.get(c.kind, 0) + 1
    ratios = [c.mse / c.minmax_mse for c in chosen.values() if c.minmax_mse > 0]
    return {"tensors": len(chosen), "won_by": dict(sorted(won.items())),
            "median_mse_ratio_to_minmax": float(np.median(ratios)) if ratios else 1.0}
