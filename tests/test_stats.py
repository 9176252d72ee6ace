"""The one percentile helper every latency report uses (e3dpsm.utils.stats), against an
explicit rank-interpolation loop, and the profile's latency summary built on it."""
from __future__ import annotations

import math

import numpy as np
import pytest

from e3dpsm.profiles.latency import latency_summary
from e3dpsm.utils.stats import percentiles


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
