"""The task budget (e3dpsm/budget.py) against independent references: the metrics module's
pooled MPJPE / PA-MPJPE, an explicit loop for jitter and for the block bootstrap, hand-made
cases for the inclusive edge and the noise rule."""
from __future__ import annotations

import numpy as np
import pytest

from e3dpsm.errors import ConfigError
from e3dpsm.metrics import jitter, mpjpe, pa_mpjpe
from e3dpsm.budget import (PRECISION_SHARE, MetricChange, TaskBudget, block_sums, check_budget,
                                    paired_change)


def _streams(seed: int, lengths=(120, 80), noise=30.0):
    rng = np.random.default_rng(seed)
    gt = [np.cumsum(rng.normal(0, 5, (n, 16, 3)), axis=0) for n in lengths]
    fp32 = [g + rng.normal(0, noise, g.shape) for g in gt]
    return gt, fp32, rng


def test_point_estimates_match_pooled_metrics():
    gt, fp32, rng = _streams(0)
    graph = [f + rng.normal(0, 3.0, f.shape) for f in fp32]
    check = check_budget(graph, fp32, gt)
    pooled = lambda fn, poses: fn(np.concatenate(poses), np.concatenate(gt))  # noqa: E731
    assert check.metric("mpjpe").fp32_mm == pytest.approx(pooled(mpjpe, fp32), rel=1e-12)
    assert check.metric("mpjpe").value_mm == pytest.approx(pooled(mpjpe, graph), rel=1e-12)
    assert check.metric("pa_mpjpe").value_mm == pytest.approx(pooled(pa_mpjpe, graph), rel=1e-12)
    # jitter: frames 3..N of each sequence, never across the boundary between them
    frames = [len(g) - 2 for g in graph]
    expected = sum(jitter(g) * n for g, n in zip(graph, frames)) / sum(frames)
    assert check.metric("jitter").value_mm == pytest.approx(expected, rel=1e-12)
    change = 100 * (pooled(mpjpe, graph) / pooled(mpjpe, fp32) - 1)
    assert check.metric("mpjpe").change_pct == pytest.approx(change, rel=1e-9)
    distance = np.mean([np.linalg.norm(g - f, axis=-1).mean() * len(g) for g, f in zip(graph, fp32)]) * 2 / 200
    assert check.fidelity_mm == pytest.approx(distance, rel=1e-9)
    assert check.frames == 200 and check.sequences == 2


def test_short_rollouts_draw_at_least_twenty_blocks():
    fp32 = [np.linspace(90, 110, 200)]
    graph = [f + np.sin(np.arange(200)) for f in fp32]
    short = paired_change(graph, fp32, 1.0, "mpjpe", TaskBudget(block_frames=50))
    assert short == paired_change(graph, fp32, 1.0, "mpjpe", TaskBudget(block_frames=10))  # 200 // 20


def test_block_sums_never_cross_a_sequence():
    sums, counts = block_sums([np.array([1.0, 2.0, 3.0]), np.array([10.0, 20.0, 30.0])], 2)
    assert sums.tolist() == [3.0, 3.0, 30.0, 30.0]
    assert counts.tolist() == [2, 1, 2, 1]


def test_bootstrap_against_an_explicit_loop():
    rng = np.random.default_rng(3)
    fp32 = [rng.uniform(50, 150, 197), rng.uniform(50, 150, 41)]
    graph = [f * rng.normal(1.01, 0.05, f.shape) for f in fp32]
    budget = TaskBudget(block_frames=10, resamples=200, seed=5)
    got = paired_change(graph, fp32, 1.0, "mpjpe", budget)
    # the same draws, block by block in plain Python
    blocks = [(seq, s) for seq, f in enumerate(fp32) for s in range(0, len(f), 10)]
    picks = np.random.default_rng(5).integers(0, len(blocks), size=(200, len(blocks)))
    draws = []
    for row in picks:
        g_total = f_total = 0.0
        for b in row:
            seq, start = blocks[b]
            g_total += float(np.sum(graph[seq][start:start + 10]))
            f_total += float(np.sum(fp32[seq][start:start + 10]))
        draws.append(100 * (g_total / f_total - 1))
    assert got.upper_pct == pytest.approx(np.percentile(draws, 95), rel=1e-9)
    assert got.lower_pct == pytest.approx(np.percentile(draws, 5), rel=1e-9)
    assert got.noise_pct == pytest.approx(np.std(draws), rel=1e-9)


def test_budget_is_inclusive_at_its_upper_end():
    fp32 = [np.full(60, 100.0)]
    graph = [np.full(60, 101.0)]  # every draw: exactly the same change
    exact = paired_change(graph, fp32, 1.0, "mpjpe", TaskBudget())
    edge = exact.upper_pct
    assert paired_change(graph, fp32, edge, "mpjpe", TaskBudget()).within
    assert not paired_change(graph, fp32, np.nextafter(edge, 0), "mpjpe", TaskBudget()).within


def test_upper_end_decides_not_the_point_estimate():
    # a mean change well inside the limit whose interval is not: over budget
    rng = np.random.default_rng(1)
    fp32 = [np.full(100, 100.0)]
    graph = [100.0 * (1 + rng.normal(0.005, 0.2, 100))]
    change = paired_change(graph, fp32, 1.0, "mpjpe", TaskBudget(block_frames=1))
    assert change.change_pct < 1.0 < change.upper_pct
    assert not change.within


def test_noise_rule_and_more_frames():
    rng = np.random.default_rng(2)
    def noise(frames):
        fp32 = [rng.uniform(80, 120, frames)]
        graph = [f + rng.normal(0, 2.0, frames) for f in fp32]
        return paired_change(graph, fp32, 1.0, "mpjpe", TaskBudget(block_frames=1))
    few, many = noise(40), noise(4000)
    assert few.noise_pct > many.noise_pct * 5  # ~ 1 / sqrt(frames): 10x the frames, 1/10 the noise... here 100x
    assert not few.precise and many.precise
    assert MetricChange("x", 1, 1, 0, 0, 0, PRECISION_SHARE * 1.0, 1.0).precise  # inclusive


def test_each_metric_can_fail_on_its_own():
    rng = np.random.default_rng(4)
    t = np.arange(400)[:, None, None]
    gt = [100 * np.sin(t / 25.0 + rng.uniform(0, 6, (1, 16, 3)))]
    fp32 = [gt[0] + rng.normal(0, 20.0, (1, 16, 3))]  # a smooth model: a constant error per joint
    shaky = [f + rng.normal(0, 1.5, f.shape) for f in fp32]  # jitter rises far more than MPJPE
    check = check_budget(shaky, fp32, gt, TaskBudget(mpjpe_pct=5.0, pa_mpjpe_pct=5.0, jitter_pct=1.0))
    assert check.metric("mpjpe").within and check.metric("pa_mpjpe").within
    assert not check.metric("jitter").within and not check.within
    assert check.worst_share == pytest.approx(check.metric("jitter").upper_pct / 1.0)
    shifted = [f + np.array([0.0, 0.0, 8.0]) for f in fp32]  # a constant offset: MPJPE, not PA-MPJPE or jitter
    offset = check_budget(shifted, fp32, gt, TaskBudget())
    assert not offset.metric("mpjpe").within
    assert offset.metric("pa_mpjpe").change_pct == pytest.approx(0.0, abs=1e-6)
    assert offset.metric("jitter").change_pct == pytest.approx(0.0, abs=1e-6)


def test_identical_graph_is_within_with_zero_interval():
    gt, fp32, _ = _streams(5)
    check = check_budget(fp32, fp32, gt)
    assert check.within and check.precise and check.fidelity_mm == 0.0
    assert all(m.upper_pct == 0.0 and m.lower_pct == 0.0 for m in check.metrics)


@pytest.mark.parametrize("fields", [{"mpjpe_pct": 0}, {"jitter_pct": -1}, {"confidence": 1.0},
                                    {"confidence": 0.3}, {"block_frames": 0}, {"resamples": 5}])
def test_bad_budgets_are_refused(fields):
    with pytest.raises(ConfigError):
        TaskBudget(**fields)


def test_mismatched_frames_are_refused():
    with pytest.raises(ValueError, match="same"):
        paired_change([np.ones(10)], [np.ones(11)], 1.0, "mpjpe", TaskBudget())
    with pytest.raises(ValueError, match="positive"):
        paired_change([np.ones(10)], [np.zeros(10)], 1.0, "mpjpe", TaskBudget())
