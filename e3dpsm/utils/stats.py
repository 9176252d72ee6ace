"""Summary figures of timing samples, shared by every report that states latencies
(serve.report.json, `e3dpsm profile`, the benchmarks): one definition of p50 / p90 / p99."""
from __future__ import annotations

from typing import Sequence

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
