"""Events to LNES frames, event-stream validation, and the one definition of time windows.

Numpy only: the streaming runtime imports this module on devices without torch.

LNES (Locally Normalised Event Surface, paper eq. 1): for the events of the window
[t0, t0 + T), pixel (x, y) of channel p holds (t - t0) / T of the latest event there, and 0
where no event fell. Channel 0 is polarity 0 (negative), channel 1 polarity 1 (positive).
Coordinates are scaled from the sensor to the frame size (640 x 480 -> 256 x 192 is the
paper's 0.4 scaling; no crop) by flooring.
"""
from __future__ import annotations

import functools
from typing import Iterator

import numpy as np

from e3dpsm.errors import ConfigError, InputError

LNES_CHANNELS = 2  # one per polarity


@functools.lru_cache(maxsize=16)
def _scaling_tables(height: int, width: int, sensor_h: int, sensor_w: int) -> tuple[np.ndarray, np.ndarray]:
    """Per sensor row / column: the frame row offset (row * width) and frame column.

    Exact integer floor(c * frame / sensor); a table lookup is cheaper per event than the
    multiply-divide and cannot overflow for narrow integer inputs.
    """
    row_offset = (np.arange(sensor_h, dtype=np.intp) * height // sensor_h) * width
    column = np.arange(sensor_w, dtype=np.intp) * width // sensor_w
    row_offset.flags.writeable = False
    column.flags.writeable = False
    return row_offset, column


def events_to_lnes(
    x: np.ndarray,
    y: np.ndarray,
    t_us: np.ndarray,
    p: np.ndarray,
    t0_us: int,
    window_us: int,
    height: int = 192,
    width: int = 256,
    sensor_hw: tuple[int, int] = (480, 640),
) -> np.ndarray:
    """LNES frame float32[2, height, width] of the events in [t0_us, t0_us + window_us).

    Events outside the window are ignored; coordinates outside the sensor are clipped to
    its border. Polarity must be 0/1 (see `validate_events`).

    "Latest event wins" is implemented as a per-pixel maximum: the value (t - t0) / T grows
    with t, so the latest event at a pixel is the one with the largest value. Unlike
    relying on the write order of numpy fancy assignment (documented as unspecified for
    repeated indices), this is exact and does not even need sorted input.
    """
    if window_us <= 0:
        raise InputError(f"window length must be positive, got {window_us} us")
    sensor_h, sensor_w = int(sensor_hw[0]), int(sensor_hw[1])
    t_us = np.asarray(t_us)
    in_window = (t_us >= t0_us) & (t_us < t0_us + window_us)
    if in_window.all():  # the common case of pre-sliced windows: skip four copies
        x, y, t, p = np.asarray(x), np.asarray(y), t_us, np.asarray(p)
    else:
        x, y, t, p = (np.asarray(a)[in_window] for a in (x, y, t_us, p))

    frame = np.zeros(LNES_CHANNELS * height * width, dtype=np.float32)
    if t.size == 0:
        return frame.reshape(LNES_CHANNELS, height, width)
    if p.min() < 0 or p.max() > 1:
        raise InputError("polarity must be 0/1; convert -1/+1 streams with validate_events")

    row_offset, column = _scaling_tables(height, width, sensor_h, sensor_w)
    rows = np.clip(_as_index(y), 0, sensor_h - 1)
    cols = np.clip(_as_index(x), 0, sensor_w - 1)
    flat = row_offset[rows] + column[cols] + p.astype(np.intp) * (height * width)
    value = (t - t0_us).astype(np.float32) / np.float32(window_us)
    np.maximum.at(frame, flat, value)
    return frame.reshape(LNES_CHANNELS, height, width)


def _as_index(coord: np.ndarray) -> np.ndarray:
    if np.issubdtype(coord.dtype, np.integer):
        return coord
    return np.floor(coord).astype(np.intp)


def validate_events(
    x: np.ndarray,
    y: np.ndarray,
    t_us: np.ndarray,
    p: np.ndarray,
    sensor_hw: tuple[int, int],
    *,
    repair_polarity: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Check an event stream and return it in canonical dtypes (int32, int32, int64, uint8).

    Raises `InputError` for arrays of different lengths, NaN/inf or fractional coordinates
    or timestamps, coordinates outside the sensor, decreasing timestamps, or polarity not
    in {0, 1}. Polarity in {-1, +1} (the paper's convention) is converted to {0, 1} when
    `repair_polarity`, since the LNES uses polarity as a channel index. Empty streams pass.
    """
    arrays = {name: np.asarray(a) for name, a in (("x", x), ("y", y), ("t", t_us), ("p", p))}
    for name, a in arrays.items():
        if a.ndim != 1:
            raise InputError(f"event array {name} must be one-dimensional, got shape {a.shape}")
    lengths = {name: a.shape[0] for name, a in arrays.items()}
    if len(set(lengths.values())) > 1:
        raise InputError(f"event arrays differ in length: {lengths}")

    sensor_h, sensor_w = int(sensor_hw[0]), int(sensor_hw[1])
    x_out = _integral(arrays["x"], "x coordinate")
    y_out = _integral(arrays["y"], "y coordinate")
    t_out = _integral(arrays["t"], "timestamp")
    for name, coord, size in (("x", x_out, sensor_w), ("y", y_out, sensor_h)):
        bad = np.flatnonzero((coord < 0) | (coord >= size))
        if bad.size:
            raise InputError(
                f"event {bad[0]} has {name} = {coord[bad[0]]}, outside the sensor's 0..{size - 1} "
                f"(sensor height x width = {sensor_h} x {sensor_w}; {bad.size} events out of range)"
            )
    decreasing = np.flatnonzero(np.diff(t_out) < 0)
    if decreasing.size:
        i = decreasing[0] + 1
        raise InputError(
            f"event timestamps must be non-decreasing; t[{i}] = {t_out[i]} < t[{i - 1}] = {t_out[i - 1]}"
        )
    return x_out.astype(np.int32), y_out.astype(np.int32), t_out, _polarity(arrays["p"], repair_polarity)


def _integral(a: np.ndarray, what: str) -> np.ndarray:
    """int64 copy of `a`, refusing NaN/inf and fractional values."""
    if a.dtype == np.bool_ or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise InputError(f"{what}s must be numbers, got dtype {a.dtype}")
    if np.issubdtype(a.dtype, np.integer):
        return a.astype(np.int64)
    finite = np.isfinite(a)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise InputError(f"event {i} has a non-finite {what} ({a[i]})")
    fractional = np.flatnonzero(a != np.floor(a))
    if fractional.size:
        i = int(fractional[0])
        unit = " (microseconds)" if what == "timestamp" else ""
        raise InputError(f"event {i} has a fractional {what} ({a[i]}); expected integers{unit}")
    return a.astype(np.int64)


def _polarity(p: np.ndarray, repair: bool) -> np.ndarray:
    if p.dtype == np.bool_:
        return p.astype(np.uint8)
    if np.issubdtype(p.dtype, np.floating) and not np.isfinite(p).all():
        raise InputError("event polarity contains NaN or inf")
    # min/max first: the common case costs two passes instead of a sort (np.unique).
    low, high = (p.min(), p.max()) if p.size else (0, 0)
    if low >= 0 and high <= 1 and (p.dtype.kind in "iu" or np.all((p == 0) | (p == 1))):
        return p.astype(np.uint8)
    if repair and low >= -1 and high <= 1 and np.all((p == -1) | (p == 1)):
        return (p > 0).astype(np.uint8)  # paper convention -1/+1 -> channel index 0/1
    shown = np.unique(p)[:5].tolist()
    raise InputError(f"event polarity must be 0/1 (or -1/+1), found values {shown}")


def window_us_from_ms(window_ms: float) -> int:
    """Window length in whole microseconds (event timestamps are integer microseconds).

    Beside the window grid so that data preparation and the torch-free runtime share one
    conversion without the runtime importing the data-preparation module."""
    window_us = round(window_ms * 1000)
    if window_ms <= 0 or abs(window_us - window_ms * 1000) > 1e-6:
        raise ConfigError(f"--window-ms must be a positive whole number of microseconds, got {window_ms}")
    return int(window_us)


def window_bounds(
    t_us: np.ndarray,
    window_us: int,
    t_start_us: int | None = None,
    t_end_us: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The consecutive complete windows [s, s + T) of a sorted stream, and their events.

    Windows start at t_start_us + k * T (default: the first event) and every window ends at
    or before t_end_us (default: just after the last event), so a trailing partial window
    is not produced: a streaming consumer emits a window only once its end has passed.
    Returns (starts_us int64[K], index_ranges int64[K, 2]) with the events of window k at
    t_us[lo:hi]; empty windows have lo == hi.
    """
    if window_us <= 0:
        raise InputError(f"window length must be positive, got {window_us} us")
    t_us = np.asarray(t_us)
    if t_start_us is None or t_end_us is None:
        if t_us.size == 0:
            return np.zeros(0, np.int64), np.zeros((0, 2), np.int64)
        t_start_us = int(t_us[0]) if t_start_us is None else t_start_us
        t_end_us = int(t_us[-1]) + 1 if t_end_us is None else t_end_us
    count = max(0, (int(t_end_us) - int(t_start_us)) // int(window_us))
    starts = int(t_start_us) + np.arange(count, dtype=np.int64) * int(window_us)
    ranges = np.empty((count, 2), dtype=np.int64)
    ranges[:, 0] = np.searchsorted(t_us, starts, side="left")
    ranges[:, 1] = np.searchsorted(t_us, starts + int(window_us), side="left")
    return starts, ranges


def iter_windows(
    t_us: np.ndarray,
    window_us: int,
    t_start_us: int | None = None,
    t_end_us: int | None = None,
) -> Iterator[tuple[int, slice]]:
    """(start_us, slice into the event arrays) for each window of `window_bounds`."""
    starts, ranges = window_bounds(t_us, window_us, t_start_us, t_end_us)
    for start, (lo, hi) in zip(starts.tolist(), ranges.tolist()):
        yield start, slice(lo, hi)
