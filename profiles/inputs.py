"""LNES frames for latency runs: a prepared folder's frames, or a built-in stream of sparse
LNES frames made from synthetic events (moving edges plus sensor noise) by the same
`events_to_lnes` the pipeline uses. Sparse, real-looking inputs matter little to dense CPU
kernels but keep any sparsity-aware runtime honest."""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from e3dpsm.events import events_to_lnes

SENSOR_HW = (480, 640)


@dataclass(frozen=True)
class Frames:
    lnes: np.ndarray  # float32 [N, 2, H, W]
    window_ms: float
    source: str


def moving_edge_frames(count: int, height: int, width: int, window_ms: float, seed: int = 0,
                     edges: int = 6, events_per_window: int = 4000, noise_fraction: float = 0.1) -> Frames:
    """`count` consecutive windows of events from `edges` line segments moving across the
    sensor (as limbs would) and uniform background noise, rendered to LNES."""
    rng = np.random.default_rng(seed)
    window_us = int(round(window_ms * 1000))
    sensor_h, sensor_w = SENSOR_HW
    centres = rng.uniform((0.2 * sensor_w, 0.2 * sensor_h), (0.8 * sensor_w, 0.8 * sensor_h), size=(edges, 2))
    velocity = rng.normal(0.0, 300.0, size=(edges, 2))  # px / s
    angle, spin = rng.uniform(0, np.pi, edges), rng.normal(0.0, 2.0, edges)  # rad, rad / s
    length = rng.uniform(60, 180, edges)
    frames = np.empty((count, 2, height, width), np.float32)
    for k in range(count):
        t0 = k * window_us
        n_edge = int(events_per_window * (1 - noise_fraction))
        which = rng.integers(0, edges, n_edge)
        t = rng.uniform(t0, t0 + window_us, n_edge)
        seconds = t / 1e6
        # Positions bounce inside the sensor: a triangle wave of the unbounded motion.
        raw = centres[which] + velocity[which] * seconds[:, None]
        span = np.array([sensor_w, sensor_h], dtype=float)
        pos = span - np.abs(np.mod(raw, 2 * span) - span)
        theta = angle[which] + spin[which] * seconds
        along = rng.uniform(-0.5, 0.5, n_edge) * length[which]
        x = pos[:, 0] + along * np.cos(theta) + rng.normal(0, 1.5, n_edge)
        y = pos[:, 1] + along * np.sin(theta) + rng.normal(0, 1.5, n_edge)
        polarity = (which % 2).astype(np.int64)
        n_noise = events_per_window - n_edge
        x = np.concatenate([x, rng.uniform(0, sensor_w, n_noise)])
        y = np.concatenate([y, rng.uniform(0, sensor_h, n_noise)])
        t = np.concatenate([t, rng.uniform(t0, t0 + window_us, n_noise)])
        polarity = np.concatenate([polarity, rng.integers(0, 2, n_noise)])
        xi = np.clip(x, 0, sensor_w - 1).astype(np.int64)
        yi = np.clip(y, 0, sensor_h - 1).astype(np.int64)
        frames[k] = events_to_lnes(xi, yi, t.astype(np.int64), polarity, t0, window_us, height, width, SENSOR_HW)
    return Frames(frames, float(window_ms), f"synthetic events (seed {seed})")


def prepared_frames(root: str | os.PathLike, count: int, height: int, width: int) -> Frames:
    """The first `count` frames of the test split (else all sequences), in stream order; a
    short folder is replayed (the states keep running)."""
    from e3dpsm.data.prepared import PreparedData
    from e3dpsm.data.streams import prepared_frames as stream_frames

    data = PreparedData.open(root)
    data.check_compatible(height=height, width=width)
    split = "test" if "test" in data.splits else None
    lnes = np.stack(list(stream_frames(root, count, split)))
    names = [s.name for s in (data.split(split) if split else data.sequences)]
    return Frames(lnes, data.window_ms, f"prepared {root} ({', '.join(names[:3])}{'...' if len(names) > 3 else ''})")
