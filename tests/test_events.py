"""LNES construction, event validation and window boundaries (e3dpsm.events)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from e3dpsm.errors import InputError
from e3dpsm.events import events_to_lnes, iter_windows, validate_events, window_bounds

T = 20_000  # us
T0 = 1_000_000


def lnes(x, y, t, p, **kw):
    return events_to_lnes(np.array(x), np.array(y), np.array(t, dtype=np.int64), np.array(p, dtype=np.uint8),
                          T0, T, **kw)


def reference_lnes(x, y, t, p, t0, window, height, width, sensor_hw):
    """Event-by-event definition: scale, skip events outside the window, overwrite in order."""
    out = np.zeros((2, height, width), np.float32)
    for xi, yi, ti, pi in zip(x, y, t, p):
        if t0 <= ti < t0 + window:
            r = min(max(yi * height // sensor_hw[0], 0), height - 1)
            c = min(max(xi * width // sensor_hw[1], 0), width - 1)
            out[pi, r, c] = np.float32(ti - t0) / np.float32(window)
    return out


def test_formula_value_channel_and_position():
    frame = lnes([10, 100], [20, 200], [T0 + 5000, T0 + 15000], [1, 0])
    assert frame.shape == (2, 192, 256) and frame.dtype == np.float32
    # 0.4 scaling: (x, y) = (10, 20) -> column 4, row 8; (100, 200) -> column 40, row 80
    assert frame[1, 8, 4] == pytest.approx(0.25, abs=1e-7)
    assert frame[0, 80, 40] == pytest.approx(0.75, abs=1e-7)
    assert np.count_nonzero(frame) == 2


@pytest.mark.parametrize(("x", "column"), [(0, 0), (2, 0), (3, 1), (5, 2), (7, 2), (638, 255), (639, 255)])
def test_coordinates_are_scaled_by_0_4_and_floored(x, column):
    frame = lnes([x], [479], [T0 + 1000], [0])
    assert frame[0, 191, column] == pytest.approx(0.05, abs=1e-7)
    assert np.count_nonzero(frame) == 1


def test_other_frame_size_scales_accordingly():
    frame = lnes([639, 10], [479, 10], [T0 + 2000, T0 + 4000], [1, 1], height=96, width=128)
    assert frame.shape == (2, 96, 128)
    assert frame[1, 95, 127] == pytest.approx(0.1, abs=1e-7)
    assert frame[1, 2, 2] == pytest.approx(0.2, abs=1e-7)


def test_latest_event_wins_at_a_repeated_pixel():
    # sensor columns 0 and 2 both land in frame column 0; the other polarity is untouched
    x, y = [0, 2, 0, 1, 0], [0, 1, 0, 0, 0]
    t = [T0 + 100, T0 + 9000, T0 + 12000, T0 + 15000, T0 + 16000]
    p = [1, 1, 1, 1, 0]
    frame = lnes(x, y, t, p)
    assert frame[1, 0, 0] == pytest.approx(15000 / T, abs=1e-7)
    assert frame[0, 0, 0] == pytest.approx(16000 / T, abs=1e-7)
    # the result is defined by time, not by the order the arrays list the events in
    order = np.array([3, 0, 4, 2, 1])
    shuffled = lnes(np.array(x)[order], np.array(y)[order], np.array(t)[order], np.array(p)[order])
    np.testing.assert_array_equal(shuffled, frame)


def test_events_outside_the_window_are_ignored():
    t = [T0 - 1, T0, T0 + T - 1, T0 + T, T0 + 5 * T]
    frame = lnes([0, 100, 200, 300, 400], [0, 0, 0, 0, 0], t, [1] * 5)
    assert frame[1, 0, 0] == 0.0  # before the window
    assert frame[1, 0, 40] == 0.0  # at t0: value 0 by the formula
    assert frame[1, 0, 80] == pytest.approx((T - 1) / T, abs=1e-7)
    assert frame[1, 0, 120] == 0.0 and frame[1, 0, 160] == 0.0  # at/after t0 + T
    assert np.count_nonzero(frame) == 1


def test_empty_window_gives_zeros():
    frame = lnes([], [], [], [])
    assert frame.shape == (2, 192, 256) and not frame.any()


def test_coordinates_outside_the_sensor_are_clipped():
    frame = lnes([-5, 700], [-1, 500], [T0 + 2000, T0 + 4000], [0, 0])
    assert frame[0, 0, 0] == pytest.approx(0.1, abs=1e-7)
    assert frame[0, 191, 255] == pytest.approx(0.2, abs=1e-7)


def test_bad_polarity_and_window_are_refused():
    with pytest.raises(InputError, match="polarity"):
        events_to_lnes(np.array([1]), np.array([1]), np.array([T0]), np.array([2]), T0, T)
    with pytest.raises(InputError, match="window"):
        events_to_lnes(np.array([1]), np.array([1]), np.array([T0]), np.array([1]), T0, 0)


@st.composite
def event_streams(draw):
    n = draw(st.integers(0, 60))
    window = draw(st.integers(1, 100_000))
    ints = lambda hi: st.lists(st.integers(0, hi), min_size=n, max_size=n)  # noqa: E731
    x = np.array(draw(ints(639)), np.int64)
    y = np.array(draw(ints(479)), np.int64)
    # small coordinate ranges too, so that pixels repeat often
    if draw(st.booleans()):
        x, y = x % 6, y % 6
    times = st.one_of(st.integers(-window, 2 * window), st.sampled_from([-1, 0, window - 1, window]))  # edges
    t = np.sort(np.array(draw(st.lists(times, min_size=n, max_size=n)), np.int64))
    p = np.array(draw(ints(1)), np.uint8)
    return x, y, t, p, window


@settings(max_examples=150, deadline=None)
@given(event_streams())
def test_lnes_matches_the_event_by_event_definition(stream):
    x, y, t, p, window = stream
    frame = events_to_lnes(x, y, t, p, 0, window)
    expected = reference_lnes(x, y, t, p, 0, window, 192, 256, (480, 640))
    assert ((frame >= 0) & (frame < 1)).all()
    np.testing.assert_allclose(frame, expected, rtol=1e-6, atol=0)
    touched = np.zeros_like(frame, dtype=bool)
    inside = (t >= 0) & (t < window)
    touched[p[inside], y[inside] * 192 // 480, x[inside] * 256 // 640] = True
    assert not frame[~touched].any()  # zero wherever no event fell


# validate_events ---------------------------------------------------------------------------

HW = (480, 640)


def test_validate_returns_canonical_dtypes():
    x, y, t, p = validate_events([1.0, 2.0], np.array([3, 4], np.uint16), [10.0, 10.0], [True, False], HW)
    assert (x.dtype, y.dtype, t.dtype, p.dtype) == (np.int32, np.int32, np.int64, np.uint8)
    np.testing.assert_array_equal(t, [10, 10])
    np.testing.assert_array_equal(p, [1, 0])


def test_validate_accepts_an_empty_stream():
    x, y, t, p = validate_events([], [], [], [], HW)
    assert len(x) == len(y) == len(t) == len(p) == 0


@pytest.mark.parametrize(
    ("x", "y", "t", "p", "message"),
    [
        ([1, 2], [1, 2], [0.0, np.nan], [0, 1], "event 1 has a non-finite timestamp"),
        ([1, np.inf], [1, 2], [0, 1], [0, 1], "event 1 has a non-finite x coordinate"),
        ([1, 640], [1, 2], [0, 1], [0, 1], "event 1 has x = 640, outside the sensor's 0..639"),
        ([1, 2], [-1, 2], [0, 1], [0, 1], "event 0 has y = -1"),
        ([1, 2, 3], [1, 2, 3], [5, 7, 6], [0, 1, 0], r"non-decreasing; t\[2\] = 6 < t\[1\] = 7"),
        ([1, 2], [1, 2], [0, 1], [0, 2], r"polarity must be 0/1 \(or -1/\+1\), found values \[0, 2\]"),
        ([1.5, 2], [1, 2], [0, 1], [0, 1], "fractional x coordinate"),
        ([1, 2], [1], [0, 1], [0, 1], "differ in length"),
    ],
)
def test_validate_refuses_bad_streams(x, y, t, p, message):
    with pytest.raises(InputError, match=message):
        validate_events(np.array(x), np.array(y), np.array(t), np.array(p), HW)


def test_validate_repairs_plus_minus_one_polarity_unless_told_not_to():
    _, _, _, p = validate_events([1, 2, 3], [1, 2, 3], [0, 1, 2], [-1, 1, -1], HW)
    np.testing.assert_array_equal(p, [0, 1, 0])
    with pytest.raises(InputError, match="polarity"):
        validate_events([1, 2], [1, 2], [0, 1], [-1, 1], HW, repair_polarity=False)


# windows --------------------------------------------------------------------------------------

def test_window_bounds_are_consecutive_and_drop_the_partial_tail():
    t = np.array([100, 105, 120, 150, 151, 199, 230, 260])
    starts, ranges = window_bounds(t, 25)
    np.testing.assert_array_equal(starts, [100, 125, 150, 175, 200, 225])  # 250..275 incomplete
    np.testing.assert_array_equal(ranges, [[0, 3], [3, 3], [3, 5], [5, 6], [6, 6], [6, 7]])
    for (start, sl), (lo, hi) in zip(iter_windows(t, 25), ranges):
        assert (sl.start, sl.stop) == (lo, hi)
        assert ((t[sl] >= start) & (t[sl] < start + 25)).all()


def test_window_bounds_with_explicit_range_and_empty_stream():
    starts, ranges = window_bounds(np.array([5, 6]), 10, t_start_us=-20, t_end_us=10)
    np.testing.assert_array_equal(starts, [-20, -10, 0])
    np.testing.assert_array_equal(ranges, [[0, 0], [0, 0], [0, 2]])
    starts, ranges = window_bounds(np.array([], np.int64), 10)
    assert starts.shape == (0,) and ranges.shape == (0, 2)
