"""Synthetic generator: event statistics, ground truth consistency, determinism, CLI."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from e3dpsm.camera import ee3d_default
from e3dpsm.data.synth.body import bone_lengths
from e3dpsm.data.synth.event_sim import EventParams, EventSimulator
from e3dpsm.data.synth.generator import SynthConfig, generate_sequence
from e3dpsm.data.synth.render import intersect_capsule
from e3dpsm.data.synth.stats import sequence_stats, summarize
from e3dpsm.errors import ConfigError
from e3dpsm.joints import ACTIONS, JOINT_NAMES, LIMB_PAIRS, PARENTS

# Two actions in 1.2 s at the default resolution and rates.
REALISTIC = SynthConfig(seed=3, seconds=1.2, segment_s=0.6)
# Small and fast, for properties that do not depend on the resolution.
SMALL = SynthConfig(seed=5, seconds=0.3, render_scale=0.25, segment_s=0.15)


@pytest.fixture(scope="session")
def synth_seq():
    return generate_sequence(REALISTIC, 0)


@pytest.fixture(scope="session")
def realism(synth_seq):
    return summarize([sequence_stats(*synth_seq)])


def test_events_are_well_formed(synth_seq):
    ev = synth_seq[0].events
    assert len(ev) > 0 and ev.t_us.dtype == np.int64
    assert np.all(np.diff(ev.t_us) >= 0)
    assert ev.x.min() >= 0 and ev.x.max() < 640 and ev.y.min() >= 0 and ev.y.max() < 480
    assert set(np.unique(ev.p)) == {0, 1}
    assert ev.t_us[0] >= 0 and ev.t_us[-1] <= synth_seq[0].t_us[-1]


def test_event_rate_and_background_share_are_plausible(realism):
    assert 1e3 <= realism["events_per_20ms"]["mean"] <= 5e4
    assert 0.05 < realism["background_share"] < 0.9
    assert realism["noise_share"] < 0.2


def test_lower_limbs_are_occluded_more_than_upper_body(realism):
    occ = realism["occluded_fraction"]
    lower = np.mean([occ[n] for n in ("R_ankle", "L_ankle", "R_foot", "L_foot")])
    upper = np.mean([occ[n] for n in ("Head", "Neck", "R_shoulder", "L_shoulder")])
    assert lower > upper + 0.2
    assert 0.7 < realism["joints_in_image"] <= 1.0


def test_ground_truth_agrees_with_the_camera_model(synth_seq):
    seq, extras = synth_seq
    cam = ee3d_default()
    np.testing.assert_allclose(seq.j2d_px, cam.project(seq.j3d_m.astype(np.float64)), atol=0.05)
    visible = seq.visible.astype(bool)
    assert np.array_equal(visible, extras.in_image & ~extras.occluded)
    uv = seq.j2d_px[visible]
    assert uv.min() >= -0.5 and uv[:, 0].max() < 640 and uv[:, 1].max() < 480
    # the wearer's body is in front of the downward-looking lens
    assert np.all(seq.j3d_m[:, [10, 14], 2] > 0.5)


def test_skeleton_is_rigid_and_timed_at_the_pose_rate(synth_seq):
    seq, _ = synth_seq
    # Limb bones are rigid (the shoulder-hip "bones" of the tree bend with the spine), and
    # moving the body into the camera frame must keep them so.
    lengths = bone_lengths(seq.j3d_m.astype(np.float64))
    limbs = lengths[:, [child for _, child in LIMB_PAIRS]]
    assert limbs.std(axis=0).max() < 1e-5
    assert np.all(limbs.mean(0) > 0.15) and np.all(lengths[:, 1:].mean(0) > 0.05)
    assert np.all(np.diff(seq.t_us) == 20_000)
    assert seq.j3d_m.shape == (60, len(JOINT_NAMES), 3) and len(PARENTS) == 16
    assert len(set(seq.action.tolist())) == 2 and seq.action.max() < len(ACTIONS)


def test_action_changes_are_smooth(synth_seq):
    seq, _ = synth_seq
    step = np.linalg.norm(np.diff(seq.j3d_m, axis=0), axis=-1)  # metres per 20 ms
    assert np.count_nonzero(np.diff(seq.action)) == 1  # the sequence does switch actions
    # 0.3 m in 20 ms is 15 m/s: faster than any limb; an unblended switch of poses jumps ~1 m.
    assert step.max() < 0.3


def test_same_seed_same_data_other_seed_other_data():
    a, _ = generate_sequence(SMALL, 0)
    b, _ = generate_sequence(SMALL, 0)
    c, _ = generate_sequence(SynthConfig(**{**SMALL.to_json(), "seed": 6, "events": SMALL.events}), 0)
    for name in ("x", "y", "t_us", "p"):
        assert np.array_equal(getattr(a.events, name), getattr(b.events, name))
    assert np.array_equal(a.j3d_m, b.j3d_m) and np.array_equal(a.visible, b.visible)
    assert not np.allclose(a.j3d_m, c.j3d_m)
    assert len(a.events) != len(c.events) or not np.array_equal(a.events.t_us, c.events.t_us)


def test_event_simulator_crossing_times_and_refractory():
    params = EventParams(threshold=0.25, threshold_sigma=0.0, refractory_us=0.0)
    rng = np.random.default_rng(0)
    sim = EventSimulator(np.zeros(2), params, rng)
    ev = sim.step(np.zeros(2), np.array([1.0, -0.5]), 0.0, 1000.0)
    order = np.lexsort((ev.t_us, ev.pixel))
    np.testing.assert_allclose(ev.t_us[order], [250, 500, 750, 1000, 500, 1000], atol=1e-6)
    assert ev.p[order].tolist() == [1, 1, 1, 1, 0, 0]
    # A 300 us dead time over crossings 250 us apart keeps every second one.
    sim = EventSimulator(np.zeros(1), EventParams(0.25, 0.0, refractory_us=300.0), rng)
    ev = sim.step(np.zeros(1), np.ones(1), 0.0, 1000.0)
    np.testing.assert_allclose(ev.t_us, [250, 750], atol=1e-6)
    # ... and carries over into the next interval: the next crossing at 1250 is 500 after 750.
    ev = sim.step(np.ones(1), np.array([1.5]), 1000.0, 2000.0)
    np.testing.assert_allclose(ev.t_us, [1500, 2000], atol=1e-6)


def test_capsule_intersection_matches_ray_marching():
    rng = np.random.default_rng(1)
    a, b, r = np.array([0.1, -0.2, 1.0]), np.array([-0.1, 0.3, 1.4]), 0.1
    rays = rng.normal([0, 0, 1], 0.25, size=(400, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    t = intersect_capsule(rays, a, b, r)
    steps = np.arange(0, 3, 1e-3)
    pts = rays[:, None, :] * steps[None, :, None]
    s = np.clip(((pts - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
    inside = np.linalg.norm(pts - (a + s[..., None] * (b - a)), axis=-1) <= r
    first = np.where(inside.any(1), steps[inside.argmax(1)], np.inf)
    assert np.isfinite(first).sum() > 20 and (~np.isfinite(first)).sum() > 20
    assert np.array_equal(np.isfinite(t), np.isfinite(first))
    hit = np.isfinite(t)
    assert np.abs(t[hit] - first[hit]).max() <= 1.5e-3


@pytest.mark.parametrize("bad", [{"seconds": -1.0}, {"render_hz": 120}, {"render_scale": 0.3}])
def test_bad_config_is_a_config_error(bad):
    with pytest.raises(ConfigError):
        generate_sequence(SynthConfig(**bad), 0)


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "e3dpsm", "synth", *args], capture_output=True, text=True)


def test_cli_rejects_bad_arguments(tmp_path):
    for args in (["--sequences", "0"], ["--seconds", "-2"]):
        res = _cli("--out", str(tmp_path / "x"), *args)
        assert res.returncode == 2 and res.stderr.count("\n") == 1 and "error" in res.stderr
        assert not (tmp_path / "x").exists()


def test_cli_writes_a_layout_that_reads_back(tmp_path):
    from e3dpsm.data.layout import read_synthetic_sequence

    out = tmp_path / "ds"
    args = ["--out", str(out), "--sequences", "3", "--seconds", "0.2", "--render-scale", "0.25",
            "--workers", "1", "--seed", "5", "--preview"]
    res = _cli(*args)
    assert res.returncode == 0, res.stderr
    assert (out / "train.txt").read_text().split() == ["seq_0000"]
    assert json.loads((out / "dataset.json").read_text())["format"] == "e3dpsm-synthetic/1"
    report = json.loads((out / "report.json").read_text())
    assert report["command"] == "synth" and "events_per_20ms" in report["realism"]
    assert len(list((out / "preview").glob("*.png"))) == 6
    seq = read_synthetic_sequence(out / "seq_0000")
    again, _ = generate_sequence(SynthConfig(seed=5, seconds=0.2, render_scale=0.25), 0)
    assert np.array_equal(seq.events.t_us, again.events.t_us) and np.array_equal(seq.events.x, again.events.x)
    np.testing.assert_array_equal(seq.j3d_m, again.j3d_m)
    np.testing.assert_array_equal(seq.visible, again.visible)
    # an existing folder is refused without --force
    res = _cli(*args)
    assert res.returncode == 2 and "--force" in res.stderr


def test_room_pass_is_finite_and_exact_for_axis_aligned_rays() -> None:
    """Rays with a component of exactly +0.0 (horizontal, or parallel to a wall) must hit
    the right plane: a float division by +0.0 once sent such a ray 'behind' the floor."""
    from e3dpsm.data.synth.motion import Room
    from e3dpsm.data.synth.render import Renderer

    room = Room(half_x=3.0, half_y=4.0, height=2.5)
    renderer = Renderer(ee3d_default(), 0.25, room, np.random.default_rng(0))
    rays = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.6, 0.0, -0.8]])
    renderer.rays_t = np.ascontiguousarray(rays.T, dtype=np.float32)
    cam = np.array([1.0, -1.0, 1.5])
    with np.errstate(invalid="raise"):
        shade = renderer._room_intensity(cam, np.eye(3))
    assert np.all(np.isfinite(shade)) and np.all(shade > 0)
