"""Summary figures of timing samples, shared by every report that states latencies
(serve.report.json, `e3dpsm run`, `e3dpsm profile`, the benchmarks): one definition of p50 /
p90 / p99, read exactly from the samples (`percentiles`) or, for sessions of any length in
fixed memory, from a histogram of them (`LogHistogram`)."""
from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np

QUANTILES = (50, 90, 99)


def percentiles(samples: Sequence[float] | np.ndarray, *, digits: int | None = 3) -> dict[str, float | int | None]:
    """count, p50, p90, p99 and max of `samples` (numpy's linear interpolation), rounded to
    `digits` decimals (None: unrounded); the figures are None when there are no samples."""
    values = np.asarray(samples, dtype=np.float64).reshape(-1)
    if not values.size:
        return {"count": 0, **{f"p{q}": None for q in QUANTILES}, "max": None}
    figures = dict(zip((f"p{q}" for q in QUANTILES), np.percentile(values, QUANTILES).tolist()))
    figures["max"] = float(values.max())
    if digits is not None:
        figures = {name: round(value, digits) for name, value in figures.items()}
    return {"count": int(values.size), **figures}


class LogHistogram:
    """Samples summarised in fixed memory, for sessions of any length (the soak's flat RSS): a
    count per bin 1% wide (relative) from LOW to HIGH, plus the exact count, min, max and the
    mean of what falls outside. `summary` reads the same figures as `percentiles`, each within
    half a bin (0.5%) of the exact one for samples inside the range; mergeable across clients."""

    LOW, HIGH, GROWTH = 1e-3, 1e7, 1.01

    def __init__(self) -> None:
        self._log_growth = math.log(self.GROWTH)
        self.bins = math.ceil(math.log(self.HIGH / self.LOW) / self._log_growth)
        self.counts = np.zeros(self.bins + 2, dtype=np.int64)  # [0]: <= LOW, [1..bins]: log bins, [-1]: > HIGH
        self.outside_sums = [0.0, 0.0]  # of the values in bin 0 and in the last bin
        self.count = 0
        self.min, self.max = math.inf, -math.inf

    def _bin(self, value: float) -> int:
        if value <= self.LOW:
            return 0
        if value > self.HIGH:
            return self.bins + 1
        return min(self.bins, 1 + int(math.log(value / self.LOW) / self._log_growth))

    def add(self, value: float) -> None:
        value = float(value)
        index = self._bin(value)
        self.counts[index] += 1
        if index == 0 or index == self.bins + 1:
            self.outside_sums[index != 0] += value
        self.count += 1
        self.min, self.max = min(self.min, value), max(self.max, value)

    def extend(self, values: Iterable[float]) -> None:
        for value in values:
            self.add(value)

    def merge(self, other: LogHistogram) -> None:
        self.counts += other.counts
        self.outside_sums = [a + b for a, b in zip(self.outside_sums, other.outside_sums)]
        self.count += other.count
        self.min, self.max = min(self.min, other.min), max(self.max, other.max)

    def _order_statistic(self, k: int, below: np.ndarray) -> float:
        """The k-th smallest sample (from 0): exact at the ends, else its bin's value."""
        if k == 0:
            return self.min
        if k == self.count - 1:
            return self.max
        index = int(np.searchsorted(below, k, side="right"))
        if index == 0 or index == self.bins + 1:
            value = self.outside_sums[index != 0] / self.counts[index]
        else:
            value = self.LOW * self.GROWTH ** (index - 0.5)  # geometric centre: within 0.5% of the bin
        return min(max(value, self.min), self.max)

    def quantile(self, q: float) -> float | None:
        """The q-th percentile as numpy's linear rule reads it, each order statistic read from its bin."""
        if not self.count:
            return None
        rank = q / 100.0 * (self.count - 1)
        below = np.cumsum(self.counts)
        low, high = math.floor(rank), math.ceil(rank)
        v_low, v_high = self._order_statistic(low, below), self._order_statistic(high, below)
        return float(v_low + (rank - low) * (v_high - v_low))

    def summary(self, digits: int | None = 3) -> dict[str, float | int | None]:
        """count, p50, p90, p99, max: the shape `percentiles` gives."""
        if not self.count:
            return percentiles([])
        figures = {f"p{q}": self.quantile(q) for q in QUANTILES}
        figures["max"] = self.max
        if digits is not None:
            figures = {name: round(value, digits) for name, value in figures.items()}
        return {"count": self.count, **figures}
