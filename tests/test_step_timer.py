"""The artifact's timing beside fp32 and the interval the verdict quotes (profiles/step_timing.py)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from e3dpsm.profiles.step_timing import speedup_interval, time_beside
from _timing_helpers import ManualClock
from test_profiles_agreement import StepOnlyRunner
from e3dpsm.quantize.verdict import time_beside_fp32


def _by_loop(candidate: np.ndarray, reference: np.ndarray, chunk: int, picks: list[list[int]]) -> list[float]:
    """Speed-ups of explicitly drawn rounds, one at a time (the reference for the bootstrap)."""
    out = []
    for picked in picks:
        c = [t for r in picked for t in candidate[r * chunk:(r + 1) * chunk]]
        f = [t for r in picked for t in reference[r * chunk:(r + 1) * chunk]]
        out.append(float(np.median(f) / np.median(c)))
    return out


def test_the_interval_is_the_percentiles_of_speed_ups_over_rounds_drawn_together() -> None:
    rng = np.random.default_rng(3)
    reference = 10 + rng.gamma(2.0, 1.0, 60)
    candidate = 12 + rng.gamma(2.0, 1.0, 60)
    got = speedup_interval(candidate, reference, chunk=10, resamples=400, seed=7)
    assert got.speedup == pytest.approx(np.median(reference) / np.median(candidate))
    assert got.rounds == 6 and got.coverage == 0.8
    # The same draws, computed by hand: rounds of both graphs drawn together.
    draws_rng = np.random.default_rng(7)
    picks = [list(draws_rng.integers(0, 6, 6)) for _ in range(400)]
    expected = np.percentile(_by_loop(candidate, reference, 10, picks), [10, 90])
    assert (got.low, got.high) == pytest.approx(tuple(expected))
    assert got.low <= got.speedup <= got.high


def test_a_constant_ratio_has_no_spread_and_a_noisy_one_straddles_it() -> None:
    rng = np.random.default_rng(0)
    reference = 8 + rng.random(100)
    exact = speedup_interval(reference * 1.25, reference, chunk=10)
    assert exact.low == pytest.approx(0.8) and exact.high == pytest.approx(0.8)
    # Load that slows the candidate's rounds in half of them (a shared host): no fixed ratio.
    candidate = reference * np.repeat([0.8, 1.25] * 5, 10)
    noisy = speedup_interval(candidate, reference, chunk=10)
    assert noisy.low < 1.0 < noisy.high and noisy.high - noisy.low > 0.2


@pytest.mark.parametrize("bad", [dict(candidate=np.ones(5), reference=np.ones(6), chunk=2),
                                 dict(candidate=np.ones(0), reference=np.ones(0), chunk=2),
                                 dict(candidate=np.ones(4), reference=np.ones(4), chunk=0)])
def test_mismatched_timings_are_refused(bad) -> None:
    with pytest.raises(ValueError, match="equally long"):
        speedup_interval(bad["candidate"], bad["reference"], bad["chunk"])


def test_the_graph_is_timed_beside_its_reference_on_each_runtime(tiny_graph: Path) -> None:
    """The same graph against itself: a speed-up near 1x whose interval holds it, over the steps asked."""
    frames = np.zeros((4, *_lnes_shape(tiny_graph)), dtype=np.float32)
    timed = time_beside_fp32(tiny_graph, tiny_graph, frames, 20.0, ("onnxruntime",), 1, steps=20)["onnxruntime"]
    assert timed["timer"]["steps"] == 20 and timed["interval"]["rounds"] == 2 and timed["timer"]["runtime"] == "onnxruntime"
    assert timed["speedup_vs_fp32"] == pytest.approx(timed["fp32_p50_ms"] / timed["p50_ms"])
    assert timed["interval"]["low"] <= timed["speedup_vs_fp32"] <= timed["interval"]["high"]


def _lnes_shape(path: Path) -> tuple[int, ...]:
    import onnx

    graph = onnx.load(str(path), load_external_data=False).graph
    lnes = next(i for i in graph.input if i.name == "lnes")
    return tuple(d.dim_value for d in lnes.type.tensor_type.shape.dim[1:])


def test_one_step_rounds_are_allowed() -> None:
    """chunk=1: every step its own round (the bootstrap then resamples steps)."""
    reference = 8 + np.random.default_rng(1).random(12)
    got = speedup_interval(reference * 2.0, reference, chunk=1)
    assert got.rounds == 12 and got.speedup == pytest.approx(0.5) and got.low == pytest.approx(0.5)


def test_time_beside_reports_both_medians_in_milliseconds_and_needs_frames() -> None:
    clock = ManualClock()
    timed = time_beside(StepOnlyRunner(clock, 0.004), StepOnlyRunner(clock, 0.002), np.zeros((3, 1)), steps=6,
                        warmup=1, chunk=3, clock=clock)
    assert timed["p50_ms"] == pytest.approx(4.0) and timed["fp32_p50_ms"] == pytest.approx(2.0)
    assert timed["speedup_vs_fp32"] == pytest.approx(0.5) and timed["interval"]["rounds"] == 2
    assert timed["timer"] == {"kind": "side_by_side", "steps": 6, "warmup": 1, "chunk": 3, "frames": 3}
    with pytest.raises(ValueError, match="at least one frame"):
        time_beside(StepOnlyRunner(clock, 0), StepOnlyRunner(clock, 0), np.zeros((0, 1)), steps=2)
