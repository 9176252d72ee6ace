"""Property-based tests of the streaming runtime: chunking never changes the result, empty
chunks are harmless, out-of-order chunks are refused."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from e3dpsm.errors import InputError
from e3dpsm.events import window_bounds
from e3dpsm.runtime import EventWindower, StreamingPoseEstimator
from _runtime_helpers import (
    SENSOR_HW, WINDOW_US, chunked, exported_tiny, reference_frames, shared_session, step_frames, synthetic_stream,
)

# Stepping the graph costs milliseconds: few examples for the estimator, more for the windower.
ESTIMATOR = settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
WINDOWER = settings(max_examples=60, deadline=None)

STREAM = synthetic_stream(seed=11, windows=8, events_per_window=150, boundary_bursts=True)
N_EVENTS = STREAM[2].size
cut_points = st.lists(st.integers(0, N_EVENTS), max_size=12)


@pytest.fixture(scope="session")
def session(tmp_path_factory):
    return shared_session(str(exported_tiny(str(tmp_path_factory.getbasetemp()))[1]))


@pytest.fixture(scope="module")
def reference(session):
    starts, _, frames = reference_frames(*STREAM)
    return starts + WINDOW_US, step_frames(session, frames)[0]


def poses_of(session, chunks) -> tuple[list[int], np.ndarray]:
    estimator = StreamingPoseEstimator(session)
    poses = list(estimator.run(chunks))
    return [p.t_us for p in poses], np.stack([p.pose for p in poses])


@ESTIMATOR
@given(cuts=cut_points)
def test_any_chunking_gives_identical_poses(session, reference, cuts):
    times, poses = poses_of(session, chunked(STREAM, cuts))
    assert times == reference[0].tolist()
    np.testing.assert_array_equal(poses, reference[1])  # same frames, same graph: bit-identical


@ESTIMATOR
@given(cuts=cut_points, empties=st.lists(st.integers(0, 12), min_size=1, max_size=6))
def test_empty_chunks_are_harmless(session, reference, cuts, empties):
    chunks = chunked(STREAM, cuts)
    for position in sorted(empties, reverse=True):
        empty = (np.zeros(0), np.zeros(0, np.int16), np.zeros(0, np.int64), np.zeros(0, np.uint8))
        chunks.insert(min(position, len(chunks)), empty)
    times, poses = poses_of(session, chunks)
    assert times == reference[0].tolist()
    np.testing.assert_array_equal(poses, reference[1])


@WINDOWER
@given(split=st.integers(1, N_EVENTS - 1), data=st.data())
def test_out_of_order_chunks_raise(split, data):
    """A chunk starting before an event already received is refused, however it overlaps."""
    t = STREAM[2]
    lo = data.draw(st.integers(0, split - 1), label="lo")
    hi = data.draw(st.integers(lo + 1, N_EVENTS), label="hi")
    assume(t[lo] < t[-1])  # equal timestamps may legitimately arrive in a later chunk
    windower = EventWindower(WINDOW_US, SENSOR_HW)
    windower.push(*(a[split:] for a in STREAM))
    with pytest.raises(InputError, match="out of order"):
        windower.push(*(a[lo:hi] for a in STREAM))


@WINDOWER
@given(cuts=cut_points, start=st.one_of(st.none(), st.integers(-3 * WINDOW_US, 3 * WINDOW_US)))
def test_windower_matches_window_bounds(cuts, start):
    """The streaming cut equals the one batch definition (window_bounds), any chunking, any start."""
    t = STREAM[2]
    start_us = None if start is None else int(t[0]) + start
    expected_starts, ranges = window_bounds(t, WINDOW_US, start_us)
    windower = EventWindower(WINDOW_US, SENSOR_HW, start_us)
    windows = []
    for chunk in chunked(STREAM, cuts):
        windows += windower.push(*chunk)
    windows += windower.finish()
    assert [s for s, _ in windows] == expected_starts.tolist()
    for (_, events), (lo, hi) in zip(windows, ranges.tolist()):
        np.testing.assert_array_equal(events[2], t[lo:hi])
        np.testing.assert_array_equal(events[0], STREAM[0][lo:hi])
