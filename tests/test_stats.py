"""The one percentile helper every latency report uses (e3dpsm.utils.stats), against an
explicit rank-interpolation loop, and the profile's latency summary built on it."""
from __future__ import annotations

import math

import numpy as np
import pytest

from e3dpsm.profiles.latency import latency_summary
from e3dpsm.utils.stats import LogHistogram, percentiles


def _linear_rank_percentile(values: list[float], q: float) -> float:
    """The q-th percentile by hand: rank q/100 * (n - 1) in the sorted values, linear between neighbours."""
    ordered = sorted(values)
    rank = q / 100.0 * (len(ordered) - 1)
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (rank - low) * (ordered[high] - ordered[low])


def test_percentiles_match_an_explicit_rank_interpolation():
    values = np.random.default_rng(1).exponential(5.0, 1000).tolist()
    got = percentiles(values, digits=None)
    assert got["count"] == 1000 and got["max"] == max(values)
    for q in (50, 90, 99):
        assert got[f"p{q}"] == pytest.approx(_linear_rank_percentile(values, q), rel=1e-12)


def test_percentiles_between_two_samples_interpolate_and_round():
    got = percentiles([1.0, 2.0, 4.0, 10.0])  # ranks 1.5, 2.7, 2.97 of 0..3
    assert got == {"count": 4, "p50": 3.0, "p90": 8.2, "p99": 9.82, "max": 10.0}
    assert percentiles([0.1234567], digits=3)["p50"] == 0.123
    assert percentiles([0.1234567], digits=None)["p50"] == 0.1234567


def test_no_samples_give_none_figures():
    assert percentiles([]) == {"count": 0, "p50": None, "p90": None, "p99": None, "max": None}
    assert percentiles(np.empty(0)) == percentiles([])


def test_profile_latency_summary_is_the_shared_percentiles_in_ms():
    seconds = np.linspace(0.001, 0.100, 100)
    summary = latency_summary(seconds)
    ms = (seconds * 1e3).tolist()
    assert summary["p50"] == pytest.approx(_linear_rank_percentile(ms, 50))
    assert summary["p99"] == pytest.approx(_linear_rank_percentile(ms, 99))
    assert summary["steps"] == summary["count"] == 100
    assert (summary["min"], summary["max"], summary["mean"]) == pytest.approx((1.0, 100.0, 50.5))


# ---- LogHistogram: the same figures in fixed memory ----------------------------------------------------------
def test_log_histogram_reads_every_percentile_within_half_a_bin():
    values = np.random.default_rng(2).lognormal(2.0, 1.0, 10_000)
    histogram = LogHistogram()
    histogram.extend(values.tolist())
    ordered = np.sort(values)
    for q in range(1, 100):
        rank = q / 100 * (len(values) - 1)
        exact = _linear_rank_percentile(values.tolist(), q)
        neighbour = ordered[math.ceil(rank)]  # each order statistic read within 0.5% of itself
        assert abs(histogram.quantile(q) - exact) <= 0.005 * neighbour, q
    summary = histogram.summary(digits=None)
    assert summary["count"] == 10_000 and summary["max"] == values.max()
    assert set(summary) == set(percentiles(values))


def test_log_histogram_error_is_the_stated_half_bin_not_less():
    low, growth = LogHistogram.LOW, LogHistogram.GROWTH
    start, end = low * growth**700 * 1.0001, low * growth**701 * 0.9999  # both ends of one bin
    histogram = LogHistogram()
    histogram.extend([start, start, end])
    relative = histogram.quantile(50) / start - 1.0  # exact median: start; read: the bin's centre
    assert 0.004 < relative < 0.005


def test_log_histograms_merge_to_the_histogram_of_all_samples():
    rng = np.random.default_rng(3)
    a, b = rng.exponential(4.0, 500).tolist(), rng.exponential(9.0, 700).tolist()
    left, right, both = LogHistogram(), LogHistogram(), LogHistogram()
    left.extend(a), right.extend(b), both.extend(a + b)
    left.merge(right)
    assert left.summary() == both.summary() and left.count == 1200 and left.min == min(a + b)


def test_log_histogram_ends_and_edge_cases():
    assert LogHistogram().summary() == percentiles([])
    one = LogHistogram()
    one.add(3.21)
    assert one.summary() == {"count": 1, "p50": 3.21, "p90": 3.21, "p99": 3.21, "max": 3.21}  # clipped to min..max
    outside = LogHistogram()
    outside.extend([-5.0, -3.0, 10.0, 1e9])  # at or below 1 us, above 10^7 ms: read as their bins' means
    assert outside.quantile(0) == -5.0 and outside.quantile(100) == 1e9
    assert outside.quantile(100 / 3) == pytest.approx(-4.0)  # the second smallest, from the low bin


def test_log_histogram_memory_does_not_grow_with_samples():
    import tracemalloc

    histogram = LogHistogram()
    histogram.extend([1.0, 2.0])
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    histogram.extend(np.random.default_rng(4).exponential(5.0, 200_000).tolist())
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(stat.size_diff for stat in after.compare_to(before, "filename")
                if stat.traceback[0].filename.endswith("stats.py"))
    assert histogram.count == 200_002 and grown < 4096  # a list of 200,000 floats would be ~6.4 MB
