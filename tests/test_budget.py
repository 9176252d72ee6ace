"""The task budget (e3dpsm/budget.py) against independent references: the metrics module's
pooled MPJPE / PA-MPJPE, an explicit loop for jitter and for the block bootstrap, hand-made
cases for the inclusive edge and the noise rule."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from e3dpsm.errors import ConfigError
from e3dpsm.metrics import jitter, mpjpe, pa_mpjpe
from e3dpsm.budget import (PRECISION_SHARE, BudgetCheck, MetricChange, TaskBudget, block_sums, check_budget,
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


def _explicit_bootstrap(graph, fp32, block: int, resamples: int, seed: int) -> list[float]:
    """The paired block bootstrap's draws, block by block in plain Python."""
    blocks = [(seq, s) for seq, f in enumerate(fp32) for s in range(0, len(f), block)]
    picks = np.random.default_rng(seed).integers(0, len(blocks), size=(resamples, len(blocks)))
    draws = []
    for row in picks:
        g_total = f_total = 0.0
        for b in row:
            seq, start = blocks[b]
            g_total += float(np.sum(graph[seq][start:start + block]))
            f_total += float(np.sum(fp32[seq][start:start + block]))
        draws.append(100 * (g_total / f_total - 1))
    return draws


def test_bootstrap_against_an_explicit_loop():
    rng = np.random.default_rng(3)
    fp32 = [rng.uniform(50, 150, 197), rng.uniform(50, 150, 41)]
    graph = [f * rng.normal(1.01, 0.05, f.shape) for f in fp32]
    budget = TaskBudget(block_frames=10, resamples=200, seed=5)
    got = paired_change(graph, fp32, 1.0, "mpjpe", budget)
    draws = _explicit_bootstrap(graph, fp32, 10, 200, 5)
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
    with pytest.raises(ValueError, match=r"^mpjpe: fp32's value is 0.0; a relative budget needs a positive reference$"):
        paired_change([np.ones(10)], [np.zeros(10)], 1.0, "mpjpe", TaskBudget())


# The documented budget and bootstrap (docs/quantize.md, "The accuracy budget"): each figure
# below is read from there, not from the code.

def test_the_default_budget_is_the_documented_one():
    budget = TaskBudget()
    assert budget.limits == {"mpjpe": 1.0, "pa_mpjpe": 1.0, "jitter": 5.0}
    assert budget.block_frames == 50  # one second of 50 Hz poses
    # the one-sided 95% bound is the upper end of the 90% interval
    assert "(90% interval)" in _hand_check().table()[0]


def test_a_validated_budget_and_its_results_cannot_be_changed_afterwards():
    with pytest.raises(dataclasses.FrozenInstanceError):
        TaskBudget().mpjpe_pct = -1.0  # would skip __post_init__'s check
    check = _hand_check()
    with pytest.raises(dataclasses.FrozenInstanceError):
        check.metrics[0].upper_pct = 0.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        check.frames = 0


@pytest.mark.parametrize("fields", [{"mpjpe_pct": 0.5}, {"confidence": 0.5}, {"block_frames": 1}, {"resamples": 10}])
def test_budgets_at_the_edge_of_their_ranges_are_accepted(fields):
    assert TaskBudget(**fields).to_dict()[next(iter(fields))] == next(iter(fields.values()))


@pytest.mark.parametrize("fields, message", [
    ({"mpjpe_pct": 0}, r"^the mpjpe budget must be positive, got 0$"),
    ({"pa_mpjpe_pct": -2.0}, r"^the pa_mpjpe budget must be positive, got -2.0$"),
    ({"jitter_pct": 0.0}, r"^the jitter budget must be positive, got 0.0$"),
    ({"confidence": 0.49}, r"^the budget's confidence must be in \[0.5, 1\), got 0.49$"),
    ({"resamples": 9}, r"^the budget's bootstrap needs block_frames >= 1 and resamples >= 10$")])
def test_a_refused_budget_names_the_field_and_its_range(fields, message):
    with pytest.raises(ConfigError, match=message):
        TaskBudget(**fields)


@pytest.mark.parametrize("frames, block", [(200, 10), (30, 1)])
def test_short_rollouts_shorten_their_blocks_to_draw_twenty(frames, block):
    """200 frames: 20 blocks of 10 (not 4 of 50); 30 frames: blocks of one frame (never 0)."""
    rng = np.random.default_rng(6)
    fp32 = [rng.uniform(80, 120, frames)]
    graph = [f * rng.normal(1.0, 0.05, frames) for f in fp32]
    got = paired_change(graph, fp32, 1.0, "mpjpe", TaskBudget(resamples=50, seed=2))
    draws = _explicit_bootstrap(graph, fp32, block, 50, 2)
    assert got.noise_pct == pytest.approx(np.std(draws), rel=1e-9)
    assert got.upper_pct == pytest.approx(np.percentile(draws, 95), rel=1e-9)


def test_precision_is_a_tenth_of_each_limit():
    """docs: noisy when the bootstrap sd is over a tenth of its limit (here a 5% limit)."""
    assert MetricChange("jitter", 1, 1, 0, 0, 0, 0.5, 5.0).precise
    assert not MetricChange("jitter", 1, 1, 0, 0, 0, 0.5001, 5.0).precise


def _hand_check(uppers=(0.5, 0.2, 4.0), limits=(1.0, 1.0, 5.0), noise=(0.01, 0.01, 0.9)) -> BudgetCheck:
    metrics = tuple(MetricChange(name, 50.0, 50.1, u - 0.1, u - 0.2, u, n, lim)
                    for name, u, lim, n in zip(("mpjpe", "pa_mpjpe", "jitter"), uppers, limits, noise))
    return BudgetCheck(metrics, 300, 2, 2.5, TaskBudget())


def test_worst_share_and_fidelity_by_hand():
    check = _hand_check()
    assert check.worst_share == pytest.approx(0.8)  # jitter: 4.0 of its 5.0
    assert check.fidelity_pct == pytest.approx(5.0)  # 2.5 mm of fp32's 50 mm MPJPE
    assert check.within and not check.precise  # jitter's sd 0.9 is over a tenth of 5


def test_the_report_dict_carries_each_verdict():
    check = _hand_check(uppers=(0.5, 1.5, 4.0))
    report = check.to_dict()
    assert report["within"] is False and report["precise"] is False
    assert (report["frames"], report["sequences"], report["fidelity_mm"]) == (300, 2, 2.5)
    assert report["fidelity_pct"] == pytest.approx(5.0)
    assert report["budget"] == TaskBudget().to_dict()
    assert [(k, v["within"], v["precise"]) for k, v in report["metrics"].items()] == [
        ("mpjpe", True, True), ("pa_mpjpe", False, True), ("jitter", True, False)]
    assert report["metrics"]["jitter"]["upper_pct"] == 4.0


def test_the_report_table_by_hand():
    rows = _hand_check(uppers=(0.5, 1.5, 4.0)).table()
    assert rows[0] == "| metric | fp32 mm | graph mm | change % (90% interval) | limit % | within |"
    assert rows[1] == "|---|---:|---:|---|---:|---|"
    assert rows[2] == "| mpjpe | 50.000 | 50.100 | +0.400 (+0.300 to +0.500) | +1 | yes |"
    assert rows[3] == "| pa_mpjpe | 50.000 | 50.100 | +1.400 (+1.300 to +1.500) | +1 | **no** |"
    assert rows[4] == "| jitter | 50.000 | 50.100 | +3.900 (+3.800 to +4.000) | +5 | yes (noisy: more frames) |"
    assert len(rows) == 5


def test_sequences_must_pair_with_ground_truth_and_frames_must_exist():
    poses = [np.zeros((10, 16, 3))]
    with pytest.raises(ValueError, match=r"^need one pose array per ground-truth sequence, got 1 and 2$"):
        check_budget(poses, poses, poses * 2)
    with pytest.raises(ValueError, match=r"^mpjpe: the graph and fp32 must be measured on the same, non-empty frames$"):
        paired_change([np.zeros(0)], [np.zeros(0)], 1.0, "mpjpe", TaskBudget())
