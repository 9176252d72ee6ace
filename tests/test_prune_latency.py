"""The pruning latency model and planner (e3dpsm/compress/latency.py, plan.py) against hand
computations."""
from __future__ import annotations

import pytest

import e3dpsm
from e3dpsm.compress.latency import LatencyProfile, UnitLatency, predict_ms, summarize_profile, unit_of_node
from e3dpsm.compress.plan import Candidate, choose
from e3dpsm.compress.units import prunable_units

# tiny: stages of 2 residual blocks, deformable blocks on every stage, decoder FFN 48.
UNITS = prunable_units(e3dpsm.create_model("tiny").config)
PROFILE = LatencyProfile(run_ms=10.0, kernel_ms=6.0, nodes=100, units={
    "stages.0.block1": UnitLatency(1.0, 5), "attention.0": UnitLatency(2.0, 50),
    "attention.0.ff": UnitLatency(0.4, 2), "decoder.ffn": UnitLatency(0.6, 4)})


def test_dispatch_is_the_unexplained_run_time_per_node():
    assert PROFILE.dispatch_ms_per_node == pytest.approx((10.0 - 6.0) / 100)


@pytest.mark.parametrize("widths, expected", [
    ({}, 10.0),
    # narrowing: kernels scale with the width, dispatch stays: 10 - 1.0 * (1 - 4/8)
    ({"stages.0.block1": 4}, 9.5),
    # removal: kernels and dispatch of the unit's nodes: 10 - (1.0 + 5 * 0.04)
    ({"stages.0.block1": 0}, 8.8),
    # a removed block takes its nested feed-forward along: 10 - (2.0 + 50 * 0.04) - (0.4 + 2 * 0.04)
    ({"attention.0": 0}, 5.52),
    # narrowing inside a removed block counts as the removal, not twice
    ({"attention.0": 0, "attention.0.ff": 16}, 5.52),
    # two units: 10 - 0.5 - 0.6 * (1 - 12/48)
    ({"stages.0.block1": 4, "decoder.ffn": 12}, 9.05),
    # a unit with no profiled time saves nothing
    ({"stages.1.block1": 0}, 10.0),
])
def test_predicted_step_by_hand(widths, expected):
    assert predict_ms(PROFILE, UNITS, widths) == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("node, unit", [
    ("/stages.0/block1/conv1/Conv", "stages.0.block1"),
    ("/stages.0/block1/shortcut/Conv", None),  # stays when the branch goes
    ("/stages.0/down/Conv", None),
    ("/attention.0/ff/proj_in/MatMul", "attention.0.ff"),
    ("/attention.0/attn/GridSample", "attention.0"),
    ("/decoder/layers.0/linear2/MatMul", "decoder.ffn"),
    ("/decoder/layers.0/self_attn/q_proj/MatMul", None),
])
def test_nodes_map_to_the_most_specific_unit(node, unit):
    assert unit_of_node(node, UNITS) == unit


def test_profiles_are_frozen_records_whose_dispatch_never_goes_negative():
    """Dispatch is the run time the kernels do not explain, per node: never below zero (a
    profile whose kernels add up to more than the run, as profiling overhead can make them),
    and a profile without nodes divides by one. The record's keys are what the prune report
    writes."""
    import dataclasses

    assert LatencyProfile(5.0, 6.0, 10).dispatch_ms_per_node == 0.0
    assert LatencyProfile(10.0, 6.0, 0).dispatch_ms_per_node == pytest.approx(4.0)
    assert LatencyProfile(1.0, 0.5, 3).units == {}
    with pytest.raises(dataclasses.FrozenInstanceError):
        PROFILE.run_ms = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        PROFILE.units["attention.0"].nodes = 1
    small = LatencyProfile(3.0, 1.0, 4, {"decoder.ffn": UnitLatency(0.25, 2)})
    assert small.to_dict() == {"run_ms": 3.0, "kernel_ms": 1.0, "nodes": 4, "dispatch_ms_per_node": 0.5,
                               "units": {"decoder.ffn": {"kernel_ms": 0.25, "nodes": 2}}}


def test_a_scaled_profile_keeps_the_shares_on_another_run_time():
    """OpenVINO borrows ONNX Runtime's shares: every kernel time scaled by the ratio of the
    two runs, node counts unchanged; a profile that measured no run time cannot give a ratio
    and lends its kernel times as they are."""
    doubled = PROFILE.scaled(20.0)
    assert (doubled.run_ms, doubled.kernel_ms, doubled.nodes) == (20.0, pytest.approx(12.0), 100)
    assert doubled.units["attention.0"] == UnitLatency(pytest.approx(4.0), 50)
    assert doubled.dispatch_ms_per_node == pytest.approx(2 * PROFILE.dispatch_ms_per_node)
    half_ms = LatencyProfile(0.5, 0.25, 2, {"stages.0.block1": UnitLatency(0.125, 1)}).scaled(1.0)
    assert (half_ms.kernel_ms, half_ms.units["stages.0.block1"].kernel_ms) == (0.5, 0.25)
    unmeasured = LatencyProfile(0.0, 2.0, 5, {"decoder.ffn": UnitLatency(1.5, 3)}).scaled(7.0)
    assert (unmeasured.run_ms, unmeasured.kernel_ms, unmeasured.units["decoder.ffn"].kernel_ms) == (7.0, 2.0, 1.5)


def test_a_unit_of_no_width_saves_nothing():
    from e3dpsm.compress.latency import saved_ms

    assert saved_ms(PROFILE, "stages.0.block1", 0, 0, removed=False) == 0.0
    assert saved_ms(PROFILE, "stages.0.block1", 0, 0, removed=True) == 0.0
    assert saved_ms(PROFILE, "stages.0.block1", 8, 0, removed=True) == pytest.approx(1.0 + 5 * 0.04)


def test_profile_summary_counts_one_step_and_events_without_a_duration():
    """One run: the counts are the run's own. Session events other than model_run are not
    runs; a kernel event without a duration is a node that took no time."""
    events = [
        {"cat": "Session", "name": "session_initialization", "dur": 500000, "ts": 0},
        {"cat": "Session", "name": "model_run", "dur": 7000, "ts": 10},
        {"cat": "Node", "name": "/stages.0/block1/conv1/Conv_kernel_time", "dur": 1000},
        {"cat": "Node", "name": "/stages.0/block1/conv2/Conv_kernel_time"},
        {"cat": "Node", "name": "/stem/stem.0/Conv_kernel_time", "dur": 3000},
    ]
    profile = summarize_profile(events, UNITS)
    assert (profile.run_ms, profile.kernel_ms, profile.nodes) == (7.0, pytest.approx(4.0), 3)
    assert profile.units == {"stages.0.block1": UnitLatency(pytest.approx(1.0), 2)}
    three = summarize_profile([{"cat": "Session", "name": "model_run", "dur": d, "ts": 0} for d in (3000, 5000, 4000)]
                              + [{"cat": "Node", "name": "/stem/stem.0/Conv_kernel_time", "dur": 6000}] * 3, UNITS)
    assert (three.run_ms, three.kernel_ms, three.nodes) == (4.0, pytest.approx(6.0), 1)
    untimed = summarize_profile([{"cat": "Session", "name": "model_run", "ts": 0},
                                 {"cat": "Node", "name": "/stem/stem.0/Conv_kernel_time", "dur": 2000}], UNITS)
    assert untimed.run_ms == 0.0 and untimed.kernel_ms == pytest.approx(2.0)


def test_profile_summary_averages_per_step():
    events = [
        {"cat": "Session", "name": "model_run", "dur": 9000, "ts": 0},
        {"cat": "Session", "name": "model_run", "dur": 11000, "ts": 20000},
        {"cat": "Node", "name": "/stages.0/block1/conv1/Conv_kernel_time", "dur": 1000},
        {"cat": "Node", "name": "/stages.0/block1/conv1/Conv_kernel_time", "dur": 3000},
        {"cat": "Node", "name": "/stem/stem.0/Conv_kernel_time", "dur": 2000},
        {"cat": "Node", "name": "/stem/stem.0/Conv_kernel_time", "dur": 2000},
        {"cat": "Node", "name": "/stem/stem.0/Conv_fence_before", "dur": 50000},  # not a kernel
    ]
    profile = summarize_profile(events, UNITS)
    assert profile.run_ms == pytest.approx(10.0)  # median of 9 and 11
    assert profile.kernel_ms == pytest.approx(4.0)  # (1 + 3 + 2 + 2) / 2 steps
    assert profile.nodes == 2
    assert profile.units == {"stages.0.block1": UnitLatency(2.0, 1)}


GREEDY_PROFILE = LatencyProfile(run_ms=10.0, kernel_ms=6.0, nodes=100, units={
    "stages.0.block1": UnitLatency(2.0, 5), "attention.0": UnitLatency(1.0, 25), "decoder.ffn": UnitLatency(0.6, 4)})
# damage per ms saved: attention.0 0.5, stages.0.block1 1.0, decoder.ffn 4.0
RANKED = [
    Candidate("stages.0.block1", 4, 8, damage_mm=2.0, saved_macs=10, saved_ms=2.0),
    Candidate("attention.0", 0, 1, damage_mm=1.0, saved_macs=5, saved_ms=2.0),
    Candidate("decoder.ffn", 12, 48, damage_mm=1.8, saved_macs=10, saved_ms=0.45),
]


def test_greedy_choice_by_damage_per_millisecond():
    widths, predicted = choose(RANKED, UNITS, "latency", current=10.0, target=7.0, profile=GREEDY_PROFILE)
    # attention.0: 10 - (1.0 + 25 * 0.04) = 8.0 > 7; stages.0.block1: 8.0 - 2.0 * (1 - 4/8) = 7.0: done
    assert widths == {"attention.0": 0, "stages.0.block1": 4}
    assert predicted == pytest.approx(7.0)


def test_greedy_choice_never_nests_cuts():
    """A chosen feed-forward cut keeps its block (no removal around it), and so the block's
    saving is never counted twice."""
    cands = [*RANKED, Candidate("attention.0.ff", 16, 32, damage_mm=0.0, saved_macs=1, saved_ms=0.2)]
    widths, predicted = choose(cands, UNITS, "latency", current=10.0, target=7.0, profile=GREEDY_PROFILE)
    assert widths == {"attention.0.ff": 16, "stages.0.block1": 4, "decoder.ffn": 12}
    assert predicted == pytest.approx(10.0 - 0.0 - 1.0 - 0.6 * 0.75)  # the ff has no profiled time here
    # And the other way round: after a removal, nothing inside the removed block.
    cands = [*RANKED, Candidate("attention.0.ff", 16, 32, damage_mm=5.0, saved_macs=1, saved_ms=0.2)]
    widths, _ = choose(cands, UNITS, "latency", current=10.0, target=5.0, profile=GREEDY_PROFILE)
    assert widths.get("attention.0") == 0 and "attention.0.ff" not in widths


def test_macs_target_stops_on_the_counted_macs():
    cands = [Candidate("stages.0.block1", 4, 8, 1.0, 30, 1.0), Candidate("decoder.ffn", 12, 48, 1.0, 30, 0.5),
             Candidate("stages.1.block1", 8, 16, 1.0, 30, 0.25)]
    widths, value = choose(cands, UNITS, "macs", current=100, target=45, profile=PROFILE)
    assert widths == {"stages.0.block1": 4, "decoder.ffn": 12}  # most ms per damage first
    assert value == 40


def test_heldout_mpjpe_is_the_per_action_mean_as_evaluate_reports_it():
    """`e3dpsm evaluate`'s MPJPE: the mean over actions of each action's mean joint error
    (explicit numpy here), with the action names grouping the frames; and the distance to the
    teacher is the mean joint distance."""
    from types import SimpleNamespace

    import numpy as np

    from e3dpsm.compress.prune import heldout_figures

    rng = np.random.default_rng(0)
    seqs, poses = [], []
    for frames in (30, 20):
        gt = rng.normal(0, 300, (frames, 16, 3)).astype(np.float32)
        action = np.repeat([0, 2], [frames // 3, frames - frames // 3])
        seqs.append(SimpleNamespace(j3d_mm=gt, visible=np.ones((frames, 16)), action=action))
        poses.append(gt + rng.normal(0, 40, gt.shape).astype(np.float32))
    err = np.concatenate([np.linalg.norm(p - s.j3d_mm, axis=-1) for p, s in zip(poses, seqs)])  # [N, J]
    action = np.concatenate([s.action for s in seqs])
    expected = np.mean([err[action == a].mean() for a in (0, 2)])
    teacher = [p + 1.0 for p in poses]  # 1 mm off along every axis: sqrt(3) mm per joint
    got = heldout_figures(poses, seqs, teacher, ("walk", "run", "jump"))
    assert got["mpjpe_mm"] == pytest.approx(expected, rel=1e-6)
    assert got["mpjpe_frame_weighted_mm"] == pytest.approx(err.mean(), rel=1e-6)
    assert got["to_teacher_mm"] == pytest.approx(np.sqrt(3.0), rel=1e-5)


def test_profile_units_times_the_steps_after_the_warm_up(tmp_path, monkeypatch):
    """The profiled session's trace holds its warm-up runs too: what is summarised is exactly
    `steps` model runs, from the first timed run on, each with the same kernels; on the
    graph's own nodes (ONNX Runtime names them by module path), a residual block's kernels
    land on its unit."""
    import numpy as np

    from e3dpsm.compress import latency
    from e3dpsm.export import export_step

    model = e3dpsm.create_model("tiny")
    graph = export_step(model, tmp_path / "tiny.onnx")
    seen = []
    monkeypatch.setattr(latency, "summarize_profile", lambda events, units: seen.append(events) or
                        summarize_profile(events, units))
    frames = np.random.default_rng(0).random((3, model.config.in_channels, model.config.height,
                                               model.config.width), dtype=np.float32)
    profile = latency.profile_units(graph, UNITS, frames, 20.0, threads=1)
    runs = [e for e in seen[0] if e.get("cat") == "Session" and e.get("name") == "model_run"]
    kernels = [e for e in seen[0] if e.get("cat") == "Node" and e["name"].endswith("_kernel_time")]
    assert len(runs) == 60 and kernels and len(kernels) % 60 == 0
    assert min(e["ts"] for e in seen[0]) == runs[0]["ts"]
    assert profile.nodes == len(kernels) // 60 and profile.units["stages.0.block1"].nodes > 0
    latency.profile_units(graph, UNITS, frames, 20.0, threads=1, steps=5, warmup=2)
    assert sum(1 for e in seen[1] if e.get("name") == "model_run") == 5
