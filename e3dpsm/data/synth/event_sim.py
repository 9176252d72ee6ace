"""Events from log-intensity changes, following the idea of ESIM (Rebecq et al., CoRL 2018)
and v2e (Hu et al., CVPRW 2021): log intensity is interpolated linearly between two
renders and an event is emitted each time it moves one contrast threshold away from the
pixel's reference level, at the interpolated crossing time.

Model choices (each a simplification worth knowing):
* per-pixel thresholds, positive and negative, drawn once from N(C, sigma) (fixed-pattern
  mismatch); the reference level advances by one threshold per crossing;
* refractory period: crossings closer than `refractory_us` to the pixel's previous event
  are dropped, the reference still advances (the charge is lost, not deferred). Crossings
  of one pixel within one render interval are evenly spaced under linear interpolation, so
  the greedy filter is computed in closed form;
* background activity: a Poisson process per sensor pixel with random polarity.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EventParams:
    threshold: float = 0.2
    threshold_sigma: float = 0.03
    refractory_us: float = 300.0
    noise_hz_per_pixel: float = 0.05


@dataclass
class EventChunk:
    pixel: np.ndarray  # [n] flat index of the simulated pixel
    t_us: np.ndarray   # [n] float64
    p: np.ndarray      # [n] uint8, 1 = brighter


class EventSimulator:
    def __init__(self, log0: np.ndarray, params: EventParams, rng: np.random.Generator):
        n = log0.shape[0]
        floor = 0.3 * params.threshold  # a physical comparator cannot reach zero
        self.c_pos = np.maximum(rng.normal(params.threshold, params.threshold_sigma, n), floor)
        self.c_neg = np.maximum(rng.normal(params.threshold, params.threshold_sigma, n), floor)
        self.ref = log0.astype(np.float64).copy()
        self.last_t = np.full(n, -np.inf)
        self.params = params

    def step(self, log_prev: np.ndarray, log_next: np.ndarray, t0_us: float, t1_us: float) -> EventChunk:
        """Events while log intensity moves linearly from `log_prev` (at t0) to `log_next`."""
        diff = log_next - self.ref
        up = diff >= self.c_pos
        down = diff <= -self.c_neg
        idx = np.flatnonzero(up | down)
        if idx.size == 0:
            return EventChunk(idx, np.empty(0), np.empty(0, np.uint8))
        sign = np.where(up[idx], 1.0, -1.0)
        c = np.where(up[idx], self.c_pos[idx], self.c_neg[idx])
        count = np.floor(np.abs(diff[idx]) / c).astype(np.int64)
        slope = log_next[idx] - log_prev[idx]  # change over the interval
        dt = t1_us - t0_us
        # Time of the first crossing and spacing between crossings. |log_prev - ref| < c
        # holds at the start of every interval, so all crossings fall inside it.
        with np.errstate(divide="ignore", invalid="ignore"):
            frac_first = (self.ref[idx] + sign * c - log_prev[idx]) / slope
            spacing = np.abs(c / slope) * dt
        t_first = t0_us + np.clip(np.nan_to_num(frac_first, nan=1.0), 0, 1) * dt
        spacing = np.nan_to_num(spacing, nan=0.0, posinf=0.0)

        # Greedy refractory filter on an evenly spaced train: skip to the first crossing
        # past the dead time, then keep every `stride`-th one.
        refr = self.params.refractory_us
        ready_at = self.last_t[idx] + refr  # -inf for pixels that never fired
        moving = spacing > 0
        safe_spacing = np.where(moving, spacing, 1.0)
        skip = np.where(moving, np.ceil((ready_at - t_first) / safe_spacing),
                        np.where(t_first < ready_at, count, 0))
        skip = np.clip(np.nan_to_num(skip, neginf=0.0), 0, None).astype(np.int64)
        stride = np.where(moving, np.maximum(1, np.ceil(refr / safe_spacing)), count + 1).astype(np.int64)
        kept = np.where(count > skip, (count - skip - 1) // stride + 1, 0)

        self.ref[idx] += sign * c * count
        has = kept > 0
        pix, kept, skip, stride = idx[has], kept[has], skip[has], stride[has]
        t_first, spacing, sign = t_first[has], spacing[has], sign[has]
        # Expand to one row per emitted event.
        rows = np.repeat(np.arange(pix.size), kept)
        rank = np.arange(rows.size) - np.repeat(np.cumsum(kept) - kept, kept)
        order_k = skip[rows] + rank * stride[rows]
        t = t_first[rows] + order_k * spacing[rows]
        self.last_t[pix] = t_first + (skip + (kept - 1) * stride) * spacing
        return EventChunk(pix[rows], t, (sign[rows] > 0).astype(np.uint8))


def noise_events(rng: np.random.Generator, n_pixels: int, rate_hz: float,
                 t0_us: float, t1_us: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Background activity over [t0, t1): (sensor pixel index, t_us, polarity)."""
    n = rng.poisson(rate_hz * n_pixels * (t1_us - t0_us) * 1e-6)
    return (rng.integers(0, n_pixels, n), rng.uniform(t0_us, t1_us, n),
            rng.integers(0, 2, n).astype(np.uint8))
