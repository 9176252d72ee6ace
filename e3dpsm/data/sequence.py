"""In-memory form of one recorded (or synthesised) sequence, whatever its on-disk layout.

Both the synthetic generator and the EE3D reader produce a `Sequence`; `prepare` consumes it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SENSOR_HW: tuple[int, int] = (480, 640)  # EE3D head-mounted camera, (height, width)


@dataclass
class EventStream:
    """Events in sensor coordinates. x, y: integer pixels; t_us: int64 microseconds,
    non-decreasing; p: polarity 0/1 (uint8)."""

    x: np.ndarray
    y: np.ndarray
    t_us: np.ndarray
    p: np.ndarray
    sensor_hw: tuple[int, int] = SENSOR_HW

    def __len__(self) -> int:
        return int(self.t_us.shape[0])


@dataclass
class Sequence:
    """One sequence: events plus ground truth sampled at pose timestamps.

    j3d_m: float32 [F, 16, 3], joints in the fisheye camera frame, metres.
    j2d_px: float32 [F, 16, 2], projections in sensor pixels (u, v).
    visible: uint8 [F, 16], 1 where the joint is visible.
    t_us: int64 [F], timestamp of each pose.
    action: int16 [F], index into `action_names` (-1 where unknown).
    """

    name: str
    events: EventStream
    j3d_m: np.ndarray
    j2d_px: np.ndarray
    visible: np.ndarray
    t_us: np.ndarray
    action: np.ndarray
    action_names: tuple[str, ...] = ()
    meta: dict = field(default_factory=dict)
